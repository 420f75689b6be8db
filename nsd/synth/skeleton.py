r"""Species of the synthetic world: keypoints, skeleton tree, body primitives, joint limits.

A :class:`Species` is an articulated body: ``K`` keypoints joined in a tree
(``parents``), a *neutral* (rest) pose of its mean body, and smooth primitives
(ellipsoids) that give it a surface. Coordinates of the rest pose are in the
*body frame*: metres, x forward, y left, z up, the ground at z = 0.

Rigid segments
    Keypoint ``j`` owns the rigid segment that moves with the joint rotation at
    ``j``: the bones from ``j`` to its children and the primitives attached to
    ``j``. Forward kinematics (:func:`forward_kinematics`), with ``E`` the joint
    rotation of :func:`joint_rotation` and ``o_k = rest_k - rest_{parent(k)}``:

    .. math::
        G_0 = R_z(h)\,E(a_0),\quad X_0 = T + R_z(h)\,\mathrm{rest}_0,\qquad
        G_k = G_{p(k)} E(a_k),\quad X_k = X_{p(k)} + G_{p(k)}\, o_k

    A point ``P`` given in the rest pose on segment ``j`` is posed as
    :math:`X_j + G_j (P - \mathrm{rest}_j)`.

Joint angles
    Per joint ``(a_x, a_y, a_z)`` radians about the body axes x (roll /
    abduction), y (pitch / flexion) and z (yaw / twist), composed as
    :math:`E = R_z(a_z) R_y(a_y) R_x(a_x)`. Positive pitch turns a downward bone
    backwards and a forward bone downwards. The root's angles tilt the whole body
    (the heading is separate). Limits are per joint and axis (``joint_limits``).

Species
    ``biped``: 17 keypoints in the order of Human3.6M's 17-joint skeleton
    (H36M-like human, about 1.75 m tall), 18 ellipsoids.
    ``quadruped``: 25 keypoints of a cow (NePuMoo-like, about 2.3 m from nose
    to tail, 1.4 m at the withers), 26 ellipsoids.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nsd.core.errors import ConfigError

__all__ = [
    "BIPED",
    "QUADRUPED",
    "SPECIES",
    "Primitive",
    "Species",
    "forward_kinematics",
    "get_species",
    "joint_rotation",
]


# ------------------------------------------------------------------ rotations
def joint_rotation(angles: Tensor) -> Tensor:
    """Rotation :math:`R_z(a_z) R_y(a_y) R_x(a_x)` of joint angles.

    Args:
        angles: ``(a_x, a_y, a_z)`` radians, shape (..., 3).

    Returns:
        Rotation matrices, shape (..., 3, 3).

    Example:
        >>> R = joint_rotation(torch.tensor([0.0, 0.0, torch.pi / 2]))
        >>> torch.allclose(R @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]), atol=1e-6)
        True
    """
    cx, cy, cz = torch.cos(angles).unbind(-1)
    sx, sy, sz = torch.sin(angles).unbind(-1)
    rows = [
        [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
        [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
        [-sy, cy * sx, cy * cx],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def forward_kinematics(
    rest: Tensor, parents: Sequence[int], angles: Tensor, heading: Tensor, translation: Tensor
) -> tuple[Tensor, Tensor]:
    """Posed keypoints and segment rotations (see the module docstring).

    Args:
        rest: rest-pose keypoints in the body frame, shape (K, 3).
        parents: parent index per keypoint (-1 for the root, which must be 0);
            parents precede their children.
        angles: joint angles, shape (..., K, 3).
        heading: rotation about world z, radians, shape (...).
        translation: world position of the body-frame origin, shape (..., 3).

    Returns:
        ``(joints, rotations)``: world keypoints (..., K, 3) and segment
        rotations :math:`G_k` (..., K, 3, 3).
    """
    E = joint_rotation(angles)
    zero = torch.zeros_like(heading)
    Rh = joint_rotation(torch.stack([zero, zero, heading], dim=-1))
    G: list[Tensor] = [Rh @ E[..., 0, :, :]]
    X: list[Tensor] = [translation + (Rh @ rest[0].to(Rh))]
    for k in range(1, len(parents)):
        p = parents[k]
        offset = (rest[k] - rest[p]).to(Rh)
        X.append(X[p] + G[p] @ offset)
        G.append(G[p] @ E[..., k, :, :])
    return torch.stack(X, dim=-2), torch.stack(G, dim=-3)


# ------------------------------------------------------------------ primitives
@dataclass(frozen=True)
class Primitive:
    """One ellipsoid of a species' mean body, in the rest pose.

    Attributes:
        name: what it is (``"left_thigh"``).
        segment: keypoint whose segment carries it.
        centre: rest-pose centre, body frame, (3,) metres.
        axes: rest-pose local axes as columns (world-from-local rotation), (3, 3).
        radii: semi-axes along the local axes, (3,) metres. Local axis 2 is the
            *length* axis (scaled with limb length), axes 0 and 1 the *girth*.
        group: proportion group (``"leg"``, ``"torso"``, ...) whose length and
            girth factors scale it.
    """

    name: str
    segment: int
    centre: tuple[float, float, float]
    axes: tuple[tuple[float, ...], ...]
    radii: tuple[float, float, float]
    group: str


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _frame_along(direction, hint) -> np.ndarray:
    """Local axes (columns x, y, z) with z along ``direction`` and x towards ``hint``."""
    z = _unit(direction)
    h = np.asarray(hint, dtype=np.float64)
    x = _unit(h - (h @ z) * z)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _bone(name, segment, a, b, r_hint, r_side, group, hint=(1, 0, 0), extend=1.12) -> Primitive:
    """An ellipsoid spanning the segment from ``a`` to ``b`` (overlapping its ends)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axes = _frame_along(b - a, hint)
    half = 0.5 * np.linalg.norm(b - a) * extend
    return Primitive(
        name,
        segment,
        tuple((0.5 * (a + b)).tolist()),
        tuple(map(tuple, axes.tolist())),
        (r_hint, r_side, half),
        group,
    )


def _blob(name, segment, centre, length_axis, radii, group, hint=(0, 0, 1)) -> Primitive:
    """An ellipsoid with its length axis along ``length_axis``; radii = (hint, side, length)."""
    axes = _frame_along(length_axis, hint)
    return Primitive(
        name,
        segment,
        tuple(float(c) for c in centre),
        tuple(map(tuple, axes.tolist())),
        tuple(float(r) for r in radii),
        group,
    )


# ------------------------------------------------------------------ species
@dataclass(frozen=True, eq=False)
class Species:
    """An articulated body type (see the module docstring).

    Attributes:
        name: ``"biped"`` or ``"quadruped"``.
        category_id: COCO category id.
        keypoint_names: K names.
        parents: K parent indices (-1 for the root, keypoint 0).
        rest: rest-pose keypoints of the mean body, body frame, (K, 3) metres.
        keypoint_groups: proportion group of the bone from each keypoint's
            parent to it (the root's group scales its height).
        primitives: the ellipsoids.
        joint_limits: (K, 3, 2) lower/upper joint angle per axis, radians.
        skeleton: bones drawn in previews and COCO files, 0-based pairs.
        kpt_oks_sigmas: per-keypoint OKS constants for COCOeval (K,).
        walk_speed: preferred walking speed, m/s.
        stride_length: distance travelled per gait cycle, m (mean body).
        footprint: ``(x_back, x_front, radius)``: the capsule on the ground,
            body frame, metres, used to keep individuals apart (its ends reach
            ``x_back`` and ``x_front``).
    """

    name: str
    category_id: int
    keypoint_names: tuple[str, ...]
    parents: tuple[int, ...]
    rest: np.ndarray
    keypoint_groups: tuple[str, ...]
    primitives: tuple[Primitive, ...]
    joint_limits: np.ndarray
    skeleton: tuple[tuple[int, int], ...]
    kpt_oks_sigmas: tuple[float, ...]
    walk_speed: float
    stride_length: float
    footprint: tuple[float, float, float]

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoint_names)

    @property
    def num_primitives(self) -> int:
        return len(self.primitives)

    @property
    def groups(self) -> tuple[str, ...]:
        """Proportion groups, sorted."""
        return tuple(sorted(set(self.keypoint_groups) | {p.group for p in self.primitives}))

    def index(self, keypoint: str) -> int:
        return self.keypoint_names.index(keypoint)

    def mirror_index(self) -> tuple[int, ...]:
        """Each keypoint's counterpart on the other side (``left`` and ``right`` swapped in
        its name; itself on the midline), (K,): ``keypoints[mirror_index()]`` labels the same
        points as a body facing the other way."""
        swap = {"left": "right", "right": "left"}
        return tuple(self.index("_".join(swap.get(w, w) for w in name.split("_")))
                     for name in self.keypoint_names)

    def left_index(self) -> tuple[int, ...]:
        """The keypoints on the body's left (``left`` in their name), each paired with its
        :meth:`mirror_index` counterpart on the right."""
        return tuple(k for k, name in enumerate(self.keypoint_names) if "left" in name.split("_"))

    def primitive_index(self, name: str) -> int:
        return [p.name for p in self.primitives].index(name)

    def children(self, k: int) -> list[int]:
        return [c for c, p in enumerate(self.parents) if p == k]

    def to_json(self) -> dict:
        """Definition for ``gt/scene.json``."""
        return {
            "name": self.name,
            "category_id": self.category_id,
            "keypoint_names": list(self.keypoint_names),
            "parents": list(self.parents),
            "skeleton": [list(b) for b in self.skeleton],
            "rest_keypoints": np.round(self.rest, 6).tolist(),
            "primitives": [
                {
                    "name": p.name,
                    "segment": p.segment,
                    "centre": list(p.centre),
                    "axes": [list(r) for r in p.axes],
                    "radii": list(p.radii),
                    "group": p.group,
                }
                for p in self.primitives
            ],
            "joint_limits": np.round(self.joint_limits, 6).tolist(),
            "kpt_oks_sigmas": list(self.kpt_oks_sigmas),
        }


def _limits(k: int, table: dict[int, tuple]) -> np.ndarray:
    lim = np.zeros((k, 3, 2))
    for j, (rx, ry, rz) in table.items():
        lim[j] = [rx, ry, rz]
    return lim


def _mirror(p, side=1.0):
    return (p[0], side * p[1], p[2])


def _make_biped() -> Species:
    names = (
        "hip", "right_hip", "right_knee", "right_foot", "left_hip", "left_knee", "left_foot",
        "spine", "thorax", "neck_nose", "head", "left_shoulder", "left_elbow", "left_wrist",
        "right_shoulder", "right_elbow", "right_wrist",
    )  # fmt: skip
    parents = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)
    L = {  # left side; the right side mirrors y
        "hip": (0.0, 0.10, 0.93),
        "knee": (0.01, 0.11, 0.52),
        "foot": (0.0, 0.11, 0.09),
        "shoulder": (0.0, 0.18, 1.43),
        "elbow": (0.0, 0.25, 1.15),
        "wrist": (0.02, 0.31, 0.90),
    }
    R = {k: _mirror(v, -1.0) for k, v in L.items()}
    rest = np.array(
        [
            (0.0, 0.0, 0.96), R["hip"], R["knee"], R["foot"], L["hip"], L["knee"], L["foot"],
            (0.0, 0.0, 1.18), (0.0, 0.0, 1.42), (0.06, 0.0, 1.56), (0.02, 0.0, 1.74),
            L["shoulder"], L["elbow"], L["wrist"], R["shoulder"], R["elbow"], R["wrist"],
        ]
    )  # fmt: skip
    groups = (
        "torso", "torso", "leg", "leg", "torso", "leg", "leg", "torso", "torso", "head", "head",
        "torso", "arm", "arm", "torso", "arm", "arm",
    )  # fmt: skip
    prims = [
        _blob("pelvis", 0, (0.0, 0.0, 0.95), (0, 0, 1), (0.11, 0.165, 0.11), "torso", (1, 0, 0))
    ]
    for side, s, (hip, knee, foot) in (("right", -1.0, (1, 2, 3)), ("left", 1.0, (4, 5, 6))):
        J = L if s > 0 else R
        prims += [
            _bone(f"{side}_thigh", hip, J["hip"], J["knee"], 0.08, 0.075, "leg"),
            _bone(f"{side}_shin", knee, J["knee"], J["foot"], 0.06, 0.055, "leg"),
            _bone(
                f"{side}_sole", foot, (-0.05, 0.11 * s, 0.05), (0.18, 0.11 * s, 0.04),
                0.045, 0.05, "leg", hint=(0, 0, 1), extend=1.0,
            ),
        ]  # fmt: skip
    prims += [
        _blob("abdomen", 7, (0.0, 0.0, 1.22), (0, 0, 1), (0.10, 0.15, 0.14), "torso", (1, 0, 0)),
        _blob("chest", 8, (0.0, 0.0, 1.36), (0, 0, 1), (0.115, 0.185, 0.15), "torso", (1, 0, 0)),
        _bone("neck", 8, (0.0, 0.0, 1.42), (0.03, 0.0, 1.58), 0.055, 0.055, "head", extend=1.0),
        _blob("skull", 9, (0.02, 0.0, 1.64), (0, 0, 1), (0.10, 0.085, 0.115), "head", (1, 0, 0)),
        _blob("nose", 9, (0.115, 0.0, 1.615), (0, 0, 1), (0.03, 0.022, 0.03), "head", (1, 0, 0)),
    ]
    for side, s, (sh, el, wr) in (("left", 1.0, (11, 12, 13)), ("right", -1.0, (14, 15, 16))):
        J = L if s > 0 else R
        w = np.asarray(J["wrist"])
        hand_end = w + 0.17 * _unit(w - np.asarray(J["elbow"]))
        prims += [
            _bone(f"{side}_upper_arm", sh, J["shoulder"], J["elbow"], 0.052, 0.05, "arm"),
            _bone(f"{side}_forearm", el, J["elbow"], J["wrist"], 0.042, 0.04, "arm"),
            _bone(f"{side}_hand", wr, w, hand_end, 0.025, 0.045, "arm", extend=1.05),
        ]
    limits = _limits(
        17,
        {
            0: ((-0.15, 0.15), (-0.2, 0.4), (0.0, 0.0)),
            1: ((-0.5, 0.3), (-1.6, 0.5), (-0.5, 0.5)),
            2: ((0.0, 0.0), (0.0, 2.3), (-0.1, 0.1)),
            3: ((-0.3, 0.3), (-0.6, 0.6), (-0.3, 0.3)),
            4: ((-0.3, 0.5), (-1.6, 0.5), (-0.5, 0.5)),
            5: ((0.0, 0.0), (0.0, 2.3), (-0.1, 0.1)),
            6: ((-0.3, 0.3), (-0.6, 0.6), (-0.3, 0.3)),
            7: ((-0.3, 0.3), (-0.3, 0.8), (-0.5, 0.5)),
            8: ((-0.3, 0.3), (-0.3, 0.5), (-0.4, 0.4)),
            9: ((-0.4, 0.4), (-0.6, 0.6), (-1.0, 1.0)),
            11: ((-0.3, 1.6), (-2.5, 0.8), (-0.8, 0.8)),
            12: ((-0.2, 0.2), (-2.4, 0.0), (-0.5, 0.5)),
            13: ((-0.5, 0.5), (-0.5, 0.5), (-0.5, 0.5)),
            14: ((-1.6, 0.3), (-2.5, 0.8), (-0.8, 0.8)),
            15: ((-0.2, 0.2), (-2.4, 0.0), (-0.5, 0.5)),
            16: ((-0.5, 0.5), (-0.5, 0.5), (-0.5, 0.5)),
        },
    )
    skeleton = tuple((parents[k], k) for k in range(1, 17))
    # COCO's person sigmas where a joint corresponds, 0.08 elsewhere
    sigmas = (0.107, 0.107, 0.087, 0.089, 0.107, 0.087, 0.089, 0.1, 0.1, 0.026, 0.05,
              0.079, 0.072, 0.062, 0.079, 0.072, 0.062)  # fmt: skip
    return Species(
        name="biped",
        category_id=1,
        keypoint_names=names,
        parents=parents,
        rest=rest,
        keypoint_groups=groups,
        primitives=tuple(prims),
        joint_limits=limits,
        skeleton=skeleton,
        kpt_oks_sigmas=sigmas,
        walk_speed=1.2,
        stride_length=1.4,
        footprint=(-0.2, 0.25, 0.32),
    )


def _make_quadruped() -> Species:
    names = [
        "spine_mid", "withers", "neck", "head", "nose", "left_ear", "right_ear", "tail_base",
        "tail_tip",
    ]  # fmt: skip
    rest = [
        (0.0, 0.0, 1.28), (0.6, 0.0, 1.40), (1.02, 0.0, 1.38), (1.06, 0.0, 1.52),
        (1.42, 0.0, 1.02), (1.02, 0.24, 1.46), (1.02, -0.24, 1.46), (-0.78, 0.0, 1.34),
        (-0.86, 0.0, 0.55),
    ]  # fmt: skip
    parents = [-1, 0, 1, 2, 2, 3, 3, 0, 7]
    groups = ["torso", "torso", "neck", "head", "head", "head", "head", "torso", "tail"]
    front = ((0.58, 0.2, 1.06), (0.52, 0.2, 0.78), (0.55, 0.2, 0.42), (0.55, 0.2, 0.04))
    hind = ((-0.62, 0.2, 1.12), (-0.46, 0.22, 0.80), (-0.70, 0.2, 0.46), (-0.64, 0.2, 0.04))
    legs = {}
    for leg, pts, joints in (
        ("front_left", front, ("shoulder", "elbow", "knee", "hoof")),
        ("front_right", front, ("shoulder", "elbow", "knee", "hoof")),
        ("hind_left", hind, ("hip", "stifle", "hock", "hoof")),
        ("hind_right", hind, ("hip", "stifle", "hock", "hoof")),
    ):
        s = 1.0 if leg.endswith("left") else -1.0
        first = len(names)
        legs[leg] = list(range(first, first + 4))
        for i, (j, p) in enumerate(zip(joints, pts, strict=True)):
            names.append(f"{leg}_{j}")
            rest.append(_mirror(p, s))
            parents.append(0 if i == 0 else first + i - 1)
            groups.append("torso" if i == 0 else "leg")
    rest = np.array(rest)
    prims = [
        _blob("barrel", 0, (-0.05, 0.0, 1.12), (1, 0, 0), (0.36, 0.33, 0.78), "torso"),
        _blob("rump", 0, (-0.58, 0.0, 1.18), (1, 0, 0), (0.28, 0.30, 0.28), "torso"),
        _blob("chest", 0, (0.50, 0.0, 1.12), (1, 0, 0), (0.34, 0.30, 0.30), "torso"),
        _bone("neck", 1, (0.52, 0.0, 1.26), (1.02, 0.0, 1.40), 0.22, 0.17, "neck", (0, 0, 1), 1.1),
        _bone(
            "skull", 2, (1.02, 0.0, 1.54), (1.42, 0.0, 1.06), 0.12, 0.11, "head", (0, 0, 1), 1.08
        ),
        _blob("muzzle", 2, (1.38, 0.0, 1.08), (1, 0, 0), (0.10, 0.11, 0.10), "head"),
    ]
    for s, k in ((1.0, 5), (-1.0, 6)):
        side = "left" if s > 0 else "right"
        prims.append(
            _bone(f"{side}_ear", 3, (1.03, 0.08 * s, 1.48), rest[k], 0.025, 0.06, "head",
                  (1, 0, 0), 1.15)
        )  # fmt: skip
    tuft = rest[8] + (0, 0, 0.02)
    prims += [
        _bone("tail", 7, rest[7], rest[8], 0.035, 0.035, "tail", (1, 0, 0), 1.05),
        _blob("tail_tuft", 8, tuft, (0, 0, 1), (0.05, 0.05, 0.09), "tail", (1, 0, 0)),
    ]
    girth = {"front": ((0.11, 0.09), (0.075, 0.065), (0.05, 0.048)),
             "hind": ((0.14, 0.11), (0.08, 0.065), (0.05, 0.048))}  # fmt: skip
    for leg, idx in legs.items():
        kind = leg.split("_")[0]
        parts = (
            ("upper_arm", "forearm", "cannon") if kind == "front" else ("thigh", "gaskin", "cannon")
        )
        for i in range(3):
            prims.append(
                _bone(f"{leg}_{parts[i]}", idx[i], rest[idx[i]], rest[idx[i + 1]],
                      *girth[kind][i], "leg")
            )  # fmt: skip
        hoof = rest[idx[3]]
        prims.append(
            _blob(f"{leg}_hoof", idx[3], (hoof[0] + 0.02, hoof[1], 0.045), (1, 0, 0),
                  (0.045, 0.06, 0.08), "leg")
        )  # fmt: skip
    table = {
        0: ((-0.15, 0.15), (-0.2, 0.2), (0.0, 0.0)),
        1: ((-0.2, 0.2), (-0.4, 1.0), (-0.5, 0.5)),
        2: ((-0.3, 0.3), (-0.5, 0.7), (-0.5, 0.5)),
        3: ((-0.4, 0.4), (-0.3, 0.3), (-0.4, 0.4)),
        7: ((-0.3, 0.3), (-0.3, 0.6), (-0.8, 0.8)),
        8: ((-0.3, 0.3), (-0.3, 0.3), (-0.3, 0.3)),
    }
    for leg, idx in legs.items():
        if leg.startswith("front"):
            rng = (((-0.15, 0.15), (-0.8, 0.6), (-0.1, 0.1)), ((-0.1, 0.1), (-0.6, 0.4), (0, 0)),
                   ((0, 0), (0.0, 1.6), (0, 0)), ((0, 0), (-0.3, 1.2), (0, 0)))  # fmt: skip
        else:
            rng = (((-0.15, 0.15), (-0.7, 0.7), (-0.1, 0.1)), ((-0.1, 0.1), (-1.0, 0.3), (0, 0)),
                   ((0, 0), (-0.3, 1.2), (0, 0)), ((0, 0), (-0.5, 0.5), (0, 0)))  # fmt: skip
        for i, r in zip(idx, rng, strict=True):
            table[i] = r
    k = len(names)
    skeleton = tuple((parents[j], j) for j in range(1, k))
    sigmas = tuple(0.089 if n.endswith(("hoof", "knee", "hock")) else 0.107 for n in names)
    return Species(
        name="quadruped",
        category_id=2,
        keypoint_names=tuple(names),
        parents=tuple(parents),
        rest=rest,
        keypoint_groups=tuple(groups),
        primitives=tuple(prims),
        joint_limits=_limits(k, table),
        skeleton=skeleton,
        kpt_oks_sigmas=sigmas,
        walk_speed=1.0,
        stride_length=1.6,
        footprint=(-0.95, 1.55, 0.4),
    )


BIPED = _make_biped()
QUADRUPED = _make_quadruped()
SPECIES: dict[str, Species] = {BIPED.name: BIPED, QUADRUPED.name: QUADRUPED}


def get_species(name: str, key: str = "species") -> Species:
    """The species called ``name``; :class:`ConfigError` naming ``key`` otherwise."""
    if isinstance(name, Species):
        return name
    try:
        return SPECIES[str(name)]
    except KeyError:
        raise ConfigError(
            f"{key}: unknown species {name!r}; choose one of {sorted(SPECIES)}"
        ) from None
