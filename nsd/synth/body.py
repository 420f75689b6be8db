r"""Individuals: a species with its own proportions and texture, and their poses.

Proportions
    An individual's rest body is its species' mean body with one overall
    ``scale`` and, per proportion group (``leg``, ``arm``, ``torso``, ...), a
    ``length`` factor :math:`\lambda_g` and a ``girth`` factor :math:`\gamma_g`:

    * keypoint offsets from the parent: :math:`o_k \leftarrow s\,\lambda_{g(k)}\,o_k`;
    * primitive centres relative to their segment's joint: :math:`\times s\,\lambda_g`;
    * semi-axes: the length axis (local axis 2) :math:`\times s\,\lambda_g`, the
      two girth axes :math:`\times s\,\gamma_g`.

    The mean body has every factor 1. NNOPCS values do not depend on the
    proportions (see :mod:`nsd.synth.nnopcs`).

Pose
    :class:`Pose` holds the world translation of the body frame's origin, a
    heading (rotation about world z; 0 faces +x) and the joint angles of
    :mod:`nsd.synth.skeleton`. Its tensors may carry leading batch dimensions
    (e.g. time). :meth:`Individual.place_on_ground` sets the height so that the
    lowest point of the body touches the ground plane z = 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from nsd.core.errors import ConfigError
from nsd.synth.nnopcs import ellipsoid_half_extents, species_primitives
from nsd.synth.skeleton import Species, forward_kinematics, get_species
from nsd.synth.texture import get_texture

__all__ = [
    "GROUND_CLEARANCE",
    "KEYPOINT_HOLD_MARGIN",
    "Individual",
    "Pose",
    "PosedBody",
    "Proportions",
    "make_individual",
    "sample_proportions",
]

KEYPOINT_HOLD_MARGIN = 0.02  # m: a primitive "holds" a keypoint within this distance of it
GROUND_CLEARANCE = 1e-3  # m between the lowest body point and the ground
SCALE_RANGE = 0.08  # overall scale in 1 +- this (times proportion_variation)
LENGTH_RANGE = 0.08  # per-group length factor in 1 +- this
GIRTH_RANGE = 0.15  # per-group girth factor in 1 +- this


@dataclass(frozen=True)
class Proportions:
    """Body proportions of one individual (see the module docstring).

    Attributes:
        scale: overall scale.
        length: per-group length factors.
        girth: per-group girth factors.
    """

    scale: float = 1.0
    length: dict[str, float] = field(default_factory=dict)
    girth: dict[str, float] = field(default_factory=dict)

    def length_of(self, group: str) -> float:
        return self.scale * self.length.get(group, 1.0)

    def girth_of(self, group: str) -> float:
        return self.scale * self.girth.get(group, 1.0)

    def to_json(self) -> dict:
        return {
            "scale": round(self.scale, 6),
            "length": {k: round(v, 6) for k, v in sorted(self.length.items())},
            "girth": {k: round(v, 6) for k, v in sorted(self.girth.items())},
        }


def sample_proportions(
    species: Species, rng: np.random.Generator, variation: float = 1.0
) -> Proportions:
    """Random proportions; ``variation`` = 0 gives the mean body, 1 the default spread."""
    groups = species.groups
    u = rng.uniform(-1.0, 1.0, size=1 + 2 * len(groups)) * variation
    return Proportions(
        scale=1.0 + SCALE_RANGE * float(u[0]),
        length={
            g: 1.0 + LENGTH_RANGE * float(x)
            for g, x in zip(groups, u[1 : 1 + len(groups)], strict=True)
        },
        girth={
            g: 1.0 + GIRTH_RANGE * float(x)
            for g, x in zip(groups, u[1 + len(groups) :], strict=True)
        },
    )


@dataclass(frozen=True)
class Pose:
    """Root placement and joint angles, optionally batched.

    Attributes:
        translation: world position of the body frame's origin, (..., 3) metres.
        heading: rotation about world z, (...) radians; 0 faces +x.
        angles: joint angles (a_x, a_y, a_z) per keypoint, (..., K, 3) radians.
    """

    translation: Tensor
    heading: Tensor
    angles: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        return self.heading.shape

    def __len__(self) -> int:
        return int(self.heading.shape[0])

    def __getitem__(self, index) -> Pose:
        return Pose(self.translation[index], self.heading[index], self.angles[index])

    def to(self, dtype: torch.dtype) -> Pose:
        return Pose(self.translation.to(dtype), self.heading.to(dtype), self.angles.to(dtype))

    @staticmethod
    def stack(poses: Sequence[Pose]) -> Pose:
        """Stack unbatched poses along a new first dimension."""
        return Pose(
            torch.stack([p.translation for p in poses]),
            torch.stack([p.heading for p in poses]),
            torch.stack([p.angles for p in poses]),
        )


@dataclass(frozen=True)
class PosedBody:
    """An individual in one pose (or a batch of poses), in world coordinates.

    Attributes:
        joints: keypoints, (..., K, 3) metres.
        rotations: segment rotations :math:`G_k`, (..., K, 3, 3).
        centres: primitive centres, (..., P, 3).
        axes: primitive local axes as columns, (..., P, 3, 3).
        radii: primitive semi-axes, (P, 3).
    """

    joints: Tensor
    rotations: Tensor
    centres: Tensor
    axes: Tensor
    radii: Tensor

    def lowest_point(self) -> Tensor:
        """Height of the lowest surface point, (...)."""
        half = ellipsoid_half_extents(self.axes, self.radii)
        return (self.centres[..., 2] - half[..., 2]).amin(-1)

    def bounding_sphere(self) -> tuple[Tensor, Tensor]:
        """A sphere holding every primitive: centre (..., 3), radius (...)."""
        centre = self.centres.mean(-2)
        reach = (self.centres - centre.unsqueeze(-2)).norm(dim=-1) + self.radii.amax(-1)
        return centre, reach.amax(-1)


@dataclass(frozen=True, eq=False)
class Individual:
    """One individual: species, proportions, identity and texture.

    Build with :func:`make_individual`. The rest tensors are float64.

    Attributes:
        species: its species.
        identity: identity id (unique within a scene).
        texture_id: id of its texture (:func:`nsd.synth.texture.get_texture`).
        proportions: its proportions.
        rest: rest-pose keypoints in the body frame, (K, 3) metres.
        rest_centres: rest-pose primitive centres, (P, 3).
        rest_axes: primitive axes, (P, 3, 3).
        radii: primitive semi-axes, (P, 3).
    """

    species: Species
    identity: int
    texture_id: int
    proportions: Proportions
    rest: Tensor
    rest_centres: Tensor
    rest_axes: Tensor
    radii: Tensor

    @property
    def num_keypoints(self) -> int:
        return self.species.num_keypoints

    @cached_property
    def segments(self) -> Tensor:
        """Segment (keypoint) index of every primitive, int64 (P,)."""
        return torch.tensor([p.segment for p in self.species.primitives], dtype=torch.int64)

    @cached_property
    def texture(self):
        """Its :class:`~nsd.synth.texture.Texture`."""

        return get_texture(self.texture_id)

    @cached_property
    def holders(self) -> Tensor:
        """Which primitives hold each keypoint, bool (K, P).

        Primitive ``p`` holds keypoint ``k`` when ``p`` lies on segment ``k`` or on
        ``k``'s parent segment (so the relation does not change with the pose) and
        ``k`` is inside ``p`` grown by :data:`KEYPOINT_HOLD_MARGIN` (if no
        primitive qualifies, the nearest one of the two segments). Used for
        keypoint visibility (:mod:`nsd.synth.render`).
        """
        parents = torch.tensor(self.species.parents)
        seg = self.segments
        on = (seg[None, :] == torch.arange(self.num_keypoints)[:, None]) | (
            seg[None, :] == parents[:, None]
        )
        rel = self.rest[:, None, :] - self.rest_centres[None]
        local = (rel.unsqueeze(-2) @ self.rest_axes[None]).squeeze(-2)
        reach = ((local / (self.radii + KEYPOINT_HOLD_MARGIN)) ** 2).sum(-1)
        held = on & (reach <= 1.0)
        # unusual proportions: fall back to the nearest primitive of the two segments
        nearest = torch.where(on, reach, torch.inf).argmin(-1)
        none = ~held.any(-1)
        held[none, nearest[none]] = True
        return held

    def rest_pose(self, dtype: torch.dtype = torch.float64) -> Pose:
        """The neutral pose at the origin, facing +x, standing on the ground."""
        k = self.num_keypoints
        pose = Pose(
            torch.zeros(3, dtype=dtype),
            torch.zeros((), dtype=dtype),
            torch.zeros(k, 3, dtype=dtype),
        )
        return self.place_on_ground(pose)

    def clamp(self, pose: Pose) -> Pose:
        """The pose with every joint angle clamped to the species' limits."""
        lim = torch.as_tensor(self.species.joint_limits, dtype=pose.angles.dtype)
        return replace(
            pose, angles=torch.minimum(torch.maximum(pose.angles, lim[..., 0]), lim[..., 1])
        )

    def posed(self, pose: Pose, dtype: torch.dtype | None = None) -> PosedBody:
        """Keypoints, segment rotations and primitives in ``pose`` (batched like ``pose``)."""
        dtype = dtype or pose.angles.dtype
        pose = pose.to(dtype)
        rest = self.rest.to(dtype)
        joints, G = forward_kinematics(
            rest, self.species.parents, pose.angles, pose.heading, pose.translation
        )
        seg = self.segments
        rel = (self.rest_centres.to(dtype) - rest[seg]).unsqueeze(-1)
        Gs = G[..., seg, :, :]
        centres = joints[..., seg, :] + (Gs @ rel).squeeze(-1)
        axes = Gs @ self.rest_axes.to(dtype)
        return PosedBody(joints, G, centres, axes, self.radii.to(dtype))

    def keypoints3d(self, pose: Pose) -> Tensor:
        """World keypoints (..., K, 3) in ``pose`` (dtype of the pose)."""
        joints, _ = forward_kinematics(
            self.rest.to(pose.angles.dtype),
            self.species.parents,
            pose.angles,
            pose.heading,
            pose.translation,
        )
        return joints

    def place_on_ground(self, pose: Pose) -> Pose:
        """``pose`` with its translation's z set so that the body stands on z = 0."""
        flat = replace(
            pose, translation=pose.translation * torch.tensor([1.0, 1.0, 0.0]).to(pose.translation)
        )
        low = self.posed(flat).lowest_point()
        z = GROUND_CLEARANCE - low
        return replace(
            flat,
            translation=flat.translation
            + torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], dim=-1),
        )

    def to_json(self) -> dict:
        return {
            "identity_id": self.identity,
            "species": self.species.name,
            "category_id": self.species.category_id,
            "texture_id": self.texture_id,
            "proportions": self.proportions.to_json(),
            "rest_keypoints": np.round(self.rest.numpy(), 6).tolist(),
        }


def make_individual(
    species: str | Species,
    identity: int = 0,
    texture_id: int | None = None,
    seed: int = 0,
    proportion_variation: float = 1.0,
    proportions: Proportions | None = None,
) -> Individual:
    """Build an individual.

    Args:
        species: ``"biped"``, ``"quadruped"`` or a :class:`Species`.
        identity: its identity id; with ``seed`` it fixes the random proportions.
        texture_id: its texture (default: ``identity``). Ids below
            :data:`nsd.synth.texture.POOL_SIZE` are the fixed pool; larger ids are
            generated textures never seen in the pool.
        seed: scene seed.
        proportion_variation: spread of the random proportions (0: mean body).
        proportions: explicit proportions (overrides the random ones).

    Returns:
        The individual, with float64 rest tensors.

    Example:
        >>> cow = make_individual("quadruped", identity=3, seed=1)
        >>> cow.keypoints3d(cow.rest_pose()).shape
        torch.Size([25, 3])
    """
    sp = get_species(species)
    if proportion_variation < 0:
        raise ConfigError(f"proportion_variation: must be >= 0, got {proportion_variation}")
    if proportions is None:
        rng = np.random.default_rng(
            [int(seed) & 0xFFFFFFFF, int(identity) & 0xFFFFFFFF, sp.category_id]
        )
        proportions = sample_proportions(sp, rng, proportion_variation)
    mean_c, axes, mean_a = species_primitives(sp)
    rest_mean = torch.as_tensor(sp.rest, dtype=torch.float64)
    rest = torch.empty_like(rest_mean)
    rest[0] = rest_mean[0] * proportions.length_of(sp.keypoint_groups[0])
    for k in range(1, sp.num_keypoints):
        p = sp.parents[k]
        rest[k] = rest[p] + proportions.length_of(sp.keypoint_groups[k]) * (
            rest_mean[k] - rest_mean[p]
        )
    seg = torch.tensor([p.segment for p in sp.primitives])
    lam = torch.tensor([proportions.length_of(p.group) for p in sp.primitives], dtype=torch.float64)
    gam = torch.tensor([proportions.girth_of(p.group) for p in sp.primitives], dtype=torch.float64)
    centres = rest[seg] + lam[:, None] * (mean_c - rest_mean[seg])
    radii = mean_a * torch.stack([gam, gam, lam], dim=-1)
    return Individual(
        species=sp,
        identity=int(identity),
        texture_id=int(identity if texture_id is None else texture_id),
        proportions=proportions,
        rest=rest,
        rest_centres=centres,
        rest_axes=axes.clone(),
        radii=radii,
    )
