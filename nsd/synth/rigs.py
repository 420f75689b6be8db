"""Camera rigs of the synthetic world: rings around the area and studio corners.

Every camera is static, calibrated and looks at a target point (world: z up,
metres; OpenCV camera axes). Focal lengths come from a horizontal field of
view: :math:`f = (W / 2) / \\tan(\\mathrm{fov} / 2)`; the principal point is the
image centre :math:`((W - 1) / 2, (H - 1) / 2)` (pixel centres at integers);
pixels are square. Optional OpenCV distortion ``(k1, k2, p1, p2[, k3])`` is
shared by all cameras of a rig; the ray caster honours it.

Rigs
    ``ring_rig``: one or more horizontal rings of cameras around the origin.
    ``nepumoo_rig``: NePuMoo's 24 cameras, 3 rings of 8 at different heights.
    ``corner_rig``: 4 cameras in the corners of a square studio (8 adds the
    middles of the sides), mounted high and looking down at the centre.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence

import numpy as np

from nsd.cameras.calibration import Camera, CameraRig
from nsd.core.errors import ConfigError

__all__ = [
    "corner_rig",
    "focal_from_fov",
    "look_at",
    "make_rig",
    "nepumoo_rig",
    "rig_from_config",
    "ring_rig",
]

RIG_KINDS = ("corners", "ring", "nepumoo")


def focal_from_fov(width: int, fov_deg: float) -> float:
    """Focal length in pixels for a horizontal field of view in degrees."""
    if not 1.0 <= fov_deg < 179.0:
        raise ConfigError(f"rig.fov_deg: must be in [1, 179), got {fov_deg}")
    return (width / 2.0) / np.tan(np.deg2rad(fov_deg) / 2.0)


def look_at(
    name: str,
    centre: Sequence[float],
    target: Sequence[float],
    size: tuple[int, int],
    fov_deg: float = 60.0,
    dist: Sequence[float] | None = None,
) -> Camera:
    """A camera at ``centre`` looking at ``target`` with world z up (image "up").

    Args:
        name: camera name.
        centre: optical centre, world (3,).
        target: the point on the optical axis, world (3,).
        size: image size (width, height).
        fov_deg: horizontal field of view, degrees.
        dist: OpenCV distortion coefficients (default none).
    """
    c, tgt = np.asarray(centre, float), np.asarray(target, float)
    z = tgt - c
    if np.linalg.norm(z) < 1e-9:
        raise ConfigError(f"camera '{name}': centre and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:  # looking straight down or up
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    W, H = int(size[0]), int(size[1])
    if W <= 0 or H <= 0:
        raise ConfigError(f"image_size: must be positive (width, height), got {(W, H)}")
    f = focal_from_fov(W, fov_deg)
    K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    d = np.zeros(0) if dist is None else np.asarray(dist, float)
    return Camera(name, K, d, R, -R @ c, (W, H))


def ring_rig(
    count: int = 8,
    radius: float = 4.0,
    height: float = 1.5,
    size: tuple[int, int] = (128, 128),
    fov_deg: float = 50.0,
    target: Sequence[float] = (0.0, 0.0, 0.8),
    rings: Sequence[dict] | None = None,
    dist: Sequence[float] | None = None,
    start_deg: float = 0.0,
) -> CameraRig:
    """Cameras evenly spaced on horizontal rings around the origin.

    Args:
        count, radius, height: one ring (ignored when ``rings`` is given).
        size: image size (width, height).
        fov_deg: horizontal field of view.
        target: the point every camera looks at.
        rings: several rings, each ``{"count", "radius", "height"}`` and
            optionally ``"start_deg"``; names are ``ring<r>_cam<i>``.
        dist: shared distortion coefficients.
        start_deg: azimuth of the first camera (0: on +x).
    """
    single = rings is None
    rings = [{"count": count, "radius": radius, "height": height}] if single else list(rings)
    cams = []
    for r, ring in enumerate(rings):
        n = int(ring["count"])
        if n < 1:
            raise ConfigError(f"rig.rings[{r}].count: must be >= 1, got {n}")
        if float(ring["radius"]) <= 0:
            raise ConfigError(f"rig.rings[{r}].radius: must be > 0, got {ring['radius']}")
        a0 = np.deg2rad(float(ring.get("start_deg", start_deg)))
        for i in range(n):
            a = a0 + 2 * np.pi * i / n
            c = (ring["radius"] * np.cos(a), ring["radius"] * np.sin(a), ring["height"])
            name = f"cam{i}" if single else f"ring{r}_cam{i}"
            cams.append(look_at(name, c, target, size, fov_deg, dist))
    return CameraRig(cams, source="synthetic ring rig")


def nepumoo_rig(
    size: tuple[int, int] = (128, 96),
    radius: float = 5.0,
    heights: Sequence[float] = (0.6, 1.8, 3.4),
    fov_deg: float = 45.0,
    target: Sequence[float] = (0.0, 0.0, 0.85),
    dist: Sequence[float] | None = None,
) -> CameraRig:
    """NePuMoo's rig: 3 evenly sampled rings of 8 cameras at different heights.

    The rings are rotated by 15 degrees against each other so that no two
    cameras share an azimuth.
    """
    rings = [
        {"count": 8, "radius": radius, "height": h, "start_deg": 15.0 * i}
        for i, h in enumerate(heights)
    ]
    return ring_rig(size=size, fov_deg=fov_deg, target=target, rings=rings, dist=dist)


def corner_rig(
    count: int = 4,
    half_width: float = 3.2,
    height: float = 2.6,
    size: tuple[int, int] = (128, 128),
    fov_deg: float = 55.0,
    target: Sequence[float] = (0.0, 0.0, 0.7),
    dist: Sequence[float] | None = None,
) -> CameraRig:
    """Studio cameras in the corners of a square room (``count`` 4), plus side middles (8).

    Names are ``cam0 ..``; corners first, counter-clockwise from (+x, +y).
    """
    if count not in (4, 8):
        raise ConfigError(f"rig.count: corner rigs hold 4 or 8 cameras, got {count}")
    h = half_width
    pos = [(h, h), (-h, h), (-h, -h), (h, -h)]
    if count == 8:
        pos += [(0.0, h), (-h, 0.0), (0.0, -h), (h, 0.0)]
    cams = [
        look_at(f"cam{i}", (x, y, height), target, size, fov_deg, dist)
        for i, (x, y) in enumerate(pos)
    ]
    return CameraRig(cams, source="synthetic corner rig")


def make_rig(kind: str, size: tuple[int, int], **params) -> CameraRig:
    """A rig by name (``corners``, ``ring`` or ``nepumoo``) with keyword parameters.

    ``distortion`` (the config's name) is accepted for ``dist``.

    Raises:
        ConfigError: an unknown kind or parameter.
    """
    builders = {"corners": corner_rig, "ring": ring_rig, "nepumoo": nepumoo_rig}
    if kind not in builders:
        raise ConfigError(f"rig.kind: unknown rig {kind!r}; choose one of {list(builders)}")
    if "distortion" in params:
        if params.get("dist") is not None:
            raise ConfigError("rig: give 'distortion' or 'dist', not both")
        params["dist"] = params.pop("distortion")
    try:
        return builders[kind](size=size, **params)
    except TypeError as e:
        raise ConfigError(f"rig: bad parameters for a {kind!r} rig: {e}") from e


def rig_from_config(rig: Mapping, size: tuple[int, int]) -> CameraRig:
    """A rig from the ``rig`` mapping of a scene config.

    ``kind`` selects the builder; keys that only other kinds use are ignored
    (so ``rig.kind=nepumoo`` works on top of the corner defaults); a key that
    no kind knows raises :class:`ConfigError`. ``distortion`` is passed as ``dist``.
    """
    builders = {"corners": corner_rig, "ring": ring_rig, "nepumoo": nepumoo_rig}
    accepted = {k: set(inspect.signature(f).parameters) - {"size"} for k, f in builders.items()}
    known = set().union(*accepted.values()) | {"kind", "distortion"}
    unknown = sorted(set(rig) - known)
    if unknown:
        raise ConfigError(f"rig: unknown keys {unknown}; known: {sorted(known)}")
    kind = rig.get("kind")
    if kind not in builders:
        raise ConfigError(f"rig.kind: unknown rig {kind!r}; choose one of {list(builders)}")
    params = {k: v for k, v in rig.items() if k in accepted[kind] or k == "distortion"}
    return make_rig(kind, size, **params)
