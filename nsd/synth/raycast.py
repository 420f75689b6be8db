r"""Analytic ray casting: camera rays, ellipsoids, the ground plane and the backdrop wall.

Rays
    :func:`camera_rays` builds one ray per pixel (or per sub-pixel sample) from
    a calibrated camera with :func:`nsd.cameras.projection.pixel_to_normalized`, lens
    distortion included: the ray of pixel ``(u, v)`` leaves the optical centre
    :math:`C = -R^T t` along :math:`d = R^T (x, y, 1) / \lVert (x, y, 1) \rVert`
    where ``(x, y)`` are the undistorted normalised coordinates. A hit at
    distance ``s`` along the unit ray has camera-space depth
    :math:`Z = s / \lVert (x, y, 1) \rVert` (``z_per_distance``).

Ellipsoids
    An ellipsoid with centre ``c``, local axes ``M`` (columns) and semi-axes
    ``a`` is :math:`\{X : \lVert M^T (X - c) / a \rVert = 1\}`. In its scaled
    local frame the ray is :math:`o' + s\,d'` with :math:`o' = M^T (o - c) / a`,
    :math:`d' = M^T d / a`; with the closest approach
    :math:`s_0 = -o' \cdot d' / \lVert d' \rVert^2`, :math:`q = o' + s_0 d'`, the
    entry point is

    .. math::
        s = s_0 - \sqrt{(1 - \lVert q \rVert^2) / \lVert d' \rVert^2},

    a hit when :math:`\lVert q \rVert \le 1` and :math:`s > 0` (this form avoids
    the cancellation of the textbook discriminant). The hit's local coordinates
    :math:`u = o' + s\,d'` lie on the unit sphere; its outward normal is
    :math:`M (u / a)`, normalised.

Culling
    Rays are tested first against each individual's bounding sphere, then the
    rays that pass against every primitive's bounding sphere (one matrix
    product), and only the surviving (ray, primitive) pairs are intersected
    exactly. Everything is vectorised over rays, cameras and primitives.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from nsd.cameras.calibration import Camera, CameraRig
from nsd.cameras.projection import pixel_to_normalized
from nsd.core.errors import ConfigError

__all__ = [
    "Ellipsoids",
    "RayHits",
    "ViewRays",
    "camera_rays",
    "cast_rays",
    "intersect_cylinder_inside",
    "intersect_ellipsoids",
    "intersect_ground",
]

CULL_MARGIN = 1e-3  # m added to bounding radii (float32 rounding of the culling tests)
CHUNK_ELEMENTS = 1 << 22  # rays x primitives per culling chunk (bounds memory)


# ------------------------------------------------------------------ rays
@dataclass
class ViewRays:
    """One ray per pixel sample of every camera.

    Attributes:
        cameras: the cameras (image size set).
        origins: optical centres, (V, 3) world metres.
        directions: unit world directions, (V, H*s, W*s, 3).
        z_per_distance: camera-space depth per unit distance along the ray,
            :math:`1 / \\lVert (x, y, 1) \\rVert`, (V, H*s, W*s).
        size: image size (width, height) in pixels.
        supersample: samples per pixel side ``s`` (odd; the middle sample is
            the pixel centre).
    """

    cameras: CameraRig
    origins: Tensor
    directions: Tensor
    z_per_distance: Tensor
    size: tuple[int, int]
    supersample: int = 1
    cache: dict = field(default_factory=dict, repr=False)

    @property
    def num_views(self) -> int:
        return self.origins.shape[0]

    def flat(self) -> tuple[Tensor, Tensor]:
        """Origin index (R,) int64 and directions (R, 3) of all V*H*s*W*s rays."""
        V = self.num_views
        n = self.directions[0, ..., 0].numel()
        index = torch.arange(V).repeat_interleave(n)
        return index, self.directions.reshape(-1, 3)

    def centre_samples(self, x: Tensor) -> Tensor:
        """The pixel-centre samples of a per-sample map (V, H*s, W*s, ...) -> (V, H, W, ...)."""
        s = self.supersample
        return x if s == 1 else x[:, s // 2 :: s, s // 2 :: s]

    def pixel_average(self, x: Tensor) -> Tensor:
        """Average of the s x s samples of each pixel, (V, H*s, W*s, C) -> (V, H, W, C)."""
        s = self.supersample
        if s == 1:
            return x
        V, Hs, Ws, C = x.shape
        return x.reshape(V, Hs // s, s, Ws // s, s, C).mean(dim=(2, 4))


def _as_rig(cameras: Sequence[Camera] | CameraRig, image_size) -> CameraRig:
    rig = cameras if isinstance(cameras, CameraRig) else CameraRig(list(cameras))
    out = []
    for c in rig:
        if image_size is not None:
            size = (int(image_size[0]), int(image_size[1]))
            if size[0] <= 0 or size[1] <= 0:
                raise ConfigError(f"image_size: must be positive (width, height), got {size}")
            c = c.with_size(size) if c.size is None else (c if c.size == size else c.scaled(size))
        elif c.size is None:
            raise ConfigError(f"camera '{c.name}' has no image size; pass image_size")
        out.append(c)
    sizes = {c.size for c in out}
    if len(sizes) > 1:
        raise ConfigError(f"image_size: cameras have different sizes {sorted(sizes)}; pass one")
    return CameraRig(out, rig.source)


def camera_rays(
    cameras: Sequence[Camera] | CameraRig,
    image_size: tuple[int, int] | None = None,
    supersample: int = 1,
    dtype: torch.dtype = torch.float32,
) -> ViewRays:
    """Rays through every pixel (sample) of every camera, distortion included.

    Args:
        cameras: the cameras.
        image_size: (width, height); cameras of another size are rescaled with
            :meth:`Camera.scaled`. Default: the cameras' own (equal) size.
        supersample: odd number of samples per pixel side (anti-aliasing).
        dtype: dtype of the returned tensors (computed in float64).

    Returns:
        The :class:`ViewRays`.
    """
    if supersample < 1 or supersample % 2 == 0:
        raise ConfigError(f"supersample: must be an odd number >= 1, got {supersample}")
    rig = _as_rig(cameras, image_size)
    W, H = rig[0].size
    s = supersample
    offs = (torch.arange(s, dtype=torch.float64) - (s - 1) / 2) / s
    u = (torch.arange(W, dtype=torch.float64)[:, None] + offs).reshape(-1)
    v = (torch.arange(H, dtype=torch.float64)[:, None] + offs).reshape(-1)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    uv = torch.stack([uu, vv], dim=-1).reshape(1, -1, 2).expand(len(rig), -1, -1)
    p = rig.stacked(torch.float64)
    xy = pixel_to_normalized(uv, p.K, p.dist)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
    norm = d_cam.norm(dim=-1)
    d_world = (d_cam / norm[..., None]) @ p.R  # rows: (R^T d)^T = d^T R
    origins = -(p.R.transpose(-1, -2) @ p.t[..., None])[..., 0]
    shape = (len(rig), H * s, W * s)
    return ViewRays(
        cameras=rig,
        origins=origins.to(dtype),
        directions=d_world.reshape(*shape, 3).to(dtype),
        z_per_distance=(1.0 / norm).reshape(shape).to(dtype),
        size=(W, H),
        supersample=s,
    )


# ------------------------------------------------------------------ planes and walls
def intersect_ground(origins: Tensor, directions: Tensor, height: float = 0.0) -> Tensor:
    """Distance to the plane z = ``height`` from above, (R,); inf when missed.

    Args:
        origins: (R, 3). directions: unit, (R, 3).
    """
    dz = directions[:, 2]
    s = (height - origins[:, 2]) / torch.where(dz < 0, dz, torch.full_like(dz, -1.0))
    return torch.where(
        (dz < 0) & (origins[:, 2] > height) & (s > 0), s, torch.full_like(s, torch.inf)
    )


def intersect_cylinder_inside(origins: Tensor, directions: Tensor, radius: float) -> Tensor:
    """Distance to the vertical cylinder ``x^2 + y^2 = radius^2`` seen from inside, (R,).

    Rays from outside the cylinder or parallel to its axis give inf.
    """
    o, d = origins[:, :2], directions[:, :2]
    A = (d * d).sum(-1)
    B = (o * d).sum(-1)
    C = (o * o).sum(-1) - radius**2
    ok = (A > 1e-12) & (C < 0)
    A = torch.where(ok, A, torch.ones_like(A))
    s = (-B + torch.sqrt((B * B - A * C).clamp_min(0.0))) / A
    return torch.where(ok, s, torch.full_like(s, torch.inf))


# ------------------------------------------------------------------ ellipsoids
@dataclass(frozen=True)
class Ellipsoids:
    """Posed ellipsoids of several individuals, flattened.

    Attributes:
        centres: (P, 3). axes: local axes as columns, (P, 3, 3). radii: (P, 3).
        owner: individual index per ellipsoid, int64 (P,).
        part: primitive index within its species, int64 (P,).
        num_individuals: N (owners are 0 .. N-1).
    """

    centres: Tensor
    axes: Tensor
    radii: Tensor
    owner: Tensor
    part: Tensor
    num_individuals: int

    @staticmethod
    def concat(
        bodies: Sequence[tuple[Tensor, Tensor, Tensor]], dtype: torch.dtype = torch.float32
    ) -> Ellipsoids:
        """From per-individual ``(centres, axes, radii)`` of unbatched posed bodies."""
        if not bodies:
            return Ellipsoids(
                torch.zeros(0, 3, dtype=dtype),
                torch.zeros(0, 3, 3, dtype=dtype),
                torch.zeros(0, 3, dtype=dtype),
                torch.zeros(0, dtype=torch.int64),
                torch.zeros(0, dtype=torch.int64),
                0,
            )
        owner = torch.cat(
            [torch.full((c.shape[0],), i, dtype=torch.int64) for i, (c, _, _) in enumerate(bodies)]
        )
        part = torch.cat([torch.arange(c.shape[0]) for c, _, _ in bodies])
        return Ellipsoids(
            centres=torch.cat([c for c, _, _ in bodies]).to(dtype),
            axes=torch.cat([m for _, m, _ in bodies]).to(dtype),
            radii=torch.cat([a for _, _, a in bodies]).to(dtype),
            owner=owner,
            part=part,
            num_individuals=len(bodies),
        )

    def bounding_spheres(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per ellipsoid (centre (P, 3), radius (P,)) and per individual (N, 3), (N,)."""
        r = self.radii.amax(-1)
        N = self.num_individuals
        count = torch.zeros(N, dtype=self.centres.dtype).index_add_(
            0, self.owner, torch.ones_like(r)
        )
        centre = torch.zeros(N, 3, dtype=self.centres.dtype).index_add_(0, self.owner, self.centres)
        centre = centre / count.clamp_min(1)[:, None]
        reach = (self.centres - centre[self.owner]).norm(dim=-1) + r
        R = torch.zeros(N, dtype=r.dtype).scatter_reduce_(0, self.owner, reach, "amax")
        return self.centres, r, centre, R


@dataclass
class RayHits:
    """First hits of rays on ellipsoids.

    Attributes:
        distance: distance along the unit ray, (R,); inf when nothing is hit.
        owner: individual hit, int64 (R,); -1 when nothing is hit.
        part: primitive index within its species, int64 (R,); -1 when nothing is hit.
        local: unit-sphere coordinates ``u`` of the hit, (R, 3); 0 when nothing is hit.
        normal: unit outward world normal, (R, 3); 0 when nothing is hit.
        owner_distance: first-hit distance on each individual ignoring the
            others (amodal), (R, N); inf when missed.
    """

    distance: Tensor
    owner: Tensor
    part: Tensor
    local: Tensor
    normal: Tensor
    owner_distance: Tensor


def intersect_ellipsoids(
    origins: Tensor, directions: Tensor, centres: Tensor, axes: Tensor, radii: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Entry distance of rays into ellipsoids, pairwise (see the module docstring).

    Args:
        origins, directions: one ray per pair, (M, 3); directions unit.
        centres, axes, radii: one ellipsoid per pair, (M, 3), (M, 3, 3), (M, 3).

    Returns:
        ``(distance, local, hit)``: distance (M,) (inf when missed), unit-sphere
        coordinates of the entry point (M, 3) and the hit flag (M,).
    """
    o = ((origins - centres).unsqueeze(-2) @ axes).squeeze(-2) / radii
    d = (directions.unsqueeze(-2) @ axes).squeeze(-2) / radii
    dd = (d * d).sum(-1)
    s0 = -(o * d).sum(-1) / dd
    q = o + s0[:, None] * d
    h2 = (1.0 - (q * q).sum(-1)) / dd
    s = s0 - torch.sqrt(h2.clamp_min(0.0))
    hit = (h2 >= 0) & (s > 0)
    local = q + (s - s0)[:, None] * d
    return torch.where(hit, s, torch.full_like(s, torch.inf)), local, hit


def _candidates(
    index: Tensor, directions: Tensor, origins: Tensor, centres: Tensor, radii: Tensor
) -> Tensor:
    """Bool (R, P): ray r may hit sphere p (distance of the centre to the ray <= radius).

    Uses :math:`(c - o) \\cdot d = c \\cdot d - o \\cdot d` and a gathered
    :math:`\\lVert c - o \\rVert^2` so that one matrix product serves all rays.
    """
    tc = directions @ centres.T - (directions * origins[index]).sum(-1, keepdim=True)
    co = centres[None, :, :] - origins[:, None, :]
    cc = (co * co).sum(-1)[index]
    r = radii + CULL_MARGIN
    return (cc - tc * tc <= r * r) & (tc > -r)


def cast_rays(
    origins: Tensor, index: Tensor, directions: Tensor, ellipsoids: Ellipsoids
) -> RayHits:
    """First hits of rays on a set of posed ellipsoids (the analytic ray caster).

    Args:
        origins: ray origins, (G, 3) (one per camera).
        index: origin of each ray, int64 (R,).
        directions: unit ray directions, (R, 3).
        ellipsoids: the posed ellipsoids of N individuals.

    Returns:
        :class:`RayHits` of the R rays.
    """
    R = directions.shape[0]
    N = ellipsoids.num_individuals
    dtype = directions.dtype
    distance = torch.full((R,), torch.inf, dtype=dtype)
    owner_distance = torch.full((R * max(N, 1),), torch.inf, dtype=dtype)
    owner = torch.full((R,), -1, dtype=torch.int64)
    part = torch.full((R,), -1, dtype=torch.int64)
    local = torch.zeros(R, 3, dtype=dtype)
    normal = torch.zeros(R, 3, dtype=dtype)
    if N == 0 or R == 0:
        return RayHits(
            distance, owner, part, local, normal, owner_distance.view(R, max(N, 1))[:, :N]
        )
    e = ellipsoids
    pc, pr, ic, ir = e.bounding_spheres()
    # level 1: individuals' bounding spheres
    rays = _candidates(index, directions, origins, ic, ir).any(-1).nonzero().squeeze(-1)
    # level 2: primitives' bounding spheres, in chunks of rays
    step = max(1, CHUNK_ELEMENTS // max(1, pc.shape[0]))
    pair_ray, pair_prim = [], []
    for start in range(0, rays.numel(), step):
        r = rays[start : start + step]
        rr, pp = _candidates(index[r], directions[r], origins, pc, pr).nonzero(as_tuple=True)
        pair_ray.append(r[rr])
        pair_prim.append(pp)
    if not pair_ray:
        return RayHits(distance, owner, part, local, normal, owner_distance.view(R, N))
    ray, prim = torch.cat(pair_ray), torch.cat(pair_prim)
    # level 3: exact intersections
    s, u, hit = intersect_ellipsoids(
        origins[index[ray]], directions[ray], e.centres[prim], e.axes[prim], e.radii[prim]
    )
    ray, prim, s, u = ray[hit], prim[hit], s[hit], u[hit]
    distance.scatter_reduce_(0, ray, s, "amin")
    owner_distance.scatter_reduce_(0, ray * N + e.owner[prim], s, "amin")
    # one winning pair per ray (ties: the highest pair index)
    win = s == distance[ray]
    pair = torch.arange(ray.numel())
    best = torch.full((R,), -1, dtype=torch.int64).scatter_reduce_(0, ray[win], pair[win], "amax")
    hit_rays = (best >= 0).nonzero().squeeze(-1)
    w = best[hit_rays]
    wp = prim[w]
    owner[hit_rays] = e.owner[wp]
    part[hit_rays] = e.part[wp]
    local[hit_rays] = u[w]
    n = (e.axes[wp] @ (u[w] / e.radii[wp]).unsqueeze(-1)).squeeze(-1)
    normal[hit_rays] = n / n.norm(dim=-1, keepdim=True)
    return RayHits(distance, owner, part, local, normal, owner_distance.view(R, N))
