r"""Render individuals from calibrated cameras: images and every ground-truth map, in memory.

:func:`render_views` ray-casts (:mod:`nsd.synth.raycast`) the posed ellipsoids of
all individuals, shades them (:mod:`nsd.synth.shading`) with their texture
(:mod:`nsd.synth.texture`) looked up at their NNOPCS value
(:mod:`nsd.synth.nnopcs`), and composites them over the static backdrop
(:mod:`nsd.synth.backdrop`). It needs no disk, so training code can generate
data on the fly; it is batched over cameras and pixels.

Conventions of the returned maps (V cameras, N individuals, H x W pixels)
    * ``depth``: camera-space depth :math:`Z_c` (metres) of the individual seen
      at the pixel centre; ``inf`` where no individual is seen (background).
      The distance along the pixel's unit ray is :math:`Z_c \lVert (x, y, 1) \rVert`.
    * ``instance``: index (0..N-1, the order of ``individuals``) of the
      individual seen; -1 for background.
    * ``amodal``: per individual, the pixels its body covers when the other
      individuals are removed; ``visible`` = ``instance == n`` lies inside it.
    * ``nnopcs``: NNOPCS of the visible surface point, in [0, 1]; 0 on background.
    * boxes: ``[x0, y0, x1, y1]`` in pixel-edge coordinates (pixel ``i`` spans
      ``[i, i + 1)``), i.e. COCO's ``[x, y, w, h] = [x0, y0, x1 - x0, y1 - y0]``;
      all zeros for an empty mask.
    * keypoints: pixel coordinates with (0, 0) the centre of the top-left pixel
      (:mod:`nsd.cameras.projection`), lens distortion included.

Keypoint visibility (COCO convention)
    ``0``: the keypoint projects outside the image (or behind the camera);
    ``2``: the first surface met by the exact ray from the optical centre to
    the 3D keypoint belongs to a primitive of the same individual that *holds*
    the keypoint (:attr:`nsd.synth.body.Individual.holders`: the body part the
    joint sits in), i.e. nothing -- another individual or another part of the
    same body -- lies in front of the body part around the joint;
    ``1``: inside the image but occluded (by another individual, or by the
    individual's own body).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from nsd.cameras.calibration import Camera, CameraRig
from nsd.cameras.projection import project_points
from nsd.core.errors import ConfigError
from nsd.ops.boxes import mask_boxes_xyxy
from nsd.synth.backdrop import Backdrop
from nsd.synth.body import Individual, Pose
from nsd.synth.nnopcs import nnopcs_of
from nsd.synth.raycast import Ellipsoids, ViewRays, camera_rays, cast_rays
from nsd.synth.shading import Light, lambert

__all__ = [
    "DEFAULT_BACKDROP",
    "DEFAULT_LIGHT",
    "keypoint_visibility",
    "render_views",
]

DEFAULT_BACKDROP = Backdrop()
DEFAULT_LIGHT = Light()


def keypoint_visibility(
    individuals: Sequence[Individual],
    keypoints: Sequence[Tensor],
    rays: ViewRays,
    ellipsoids: Ellipsoids,
) -> tuple[list[Tensor], list[Tensor]]:
    """2D keypoints and their COCO visibility in every camera (see the module docstring).

    Args:
        individuals: N individuals.
        keypoints: per individual, world keypoints (K_n, 3) (float64 recommended).
        rays: the cameras (their :class:`ViewRays`).
        ellipsoids: all posed primitives (as used for rendering).

    Returns:
        ``(uv, visibility)``: per individual, pixels (V, K_n, 2) in the dtype of
        ``keypoints`` and visibility int64 (V, K_n) in {0, 1, 2}.
    """
    p = rays.cameras.stacked(torch.float64)
    W, H = rays.size
    uvs, vis = [], []
    origins = rays.origins.to(torch.float64)
    for n, (ind, X) in enumerate(zip(individuals, keypoints, strict=True)):
        Xd = X.to(torch.float64)
        uv, z = project_points(
            Xd.expand(len(rays.cameras), -1, -1), p.K, p.R, p.t, p.dist
        )
        inside = (
            (z > 0)
            & (uv[..., 0] >= -0.5)
            & (uv[..., 0] < W - 0.5)
            & (uv[..., 1] >= -0.5)
            & (uv[..., 1] < H - 0.5)
        )
        d = Xd[None] - origins[:, None]
        d = d / d.norm(dim=-1, keepdim=True)
        V, K = d.shape[:2]
        index = torch.arange(V).repeat_interleave(K)
        hits = cast_rays(rays.origins, index, d.reshape(-1, 3).to(rays.origins.dtype), ellipsoids)
        own = hits.owner.view(V, K) == n
        part = torch.where(own, hits.part.view(V, K), 0)
        held = ind.holders[torch.arange(K)[None].expand(V, K), part]
        v = torch.where(inside, torch.where(own & held, 2, 1), 0)
        uvs.append(uv.to(X.dtype))
        vis.append(v.to(torch.int64))
    return uvs, vis


def render_views(
    individuals: Sequence[Individual],
    poses: Sequence[Pose],
    cameras: Sequence[Camera] | CameraRig | ViewRays,
    image_size: tuple[int, int] | None = None,
    *,
    background: bool = True,
    supersample: int = 1,
    backdrop: Backdrop = DEFAULT_BACKDROP,
    light: Light = DEFAULT_LIGHT,
) -> dict[str, Tensor | list[Tensor]]:
    """Render N individuals in their poses from V cameras, with every ground-truth map.

    Args:
        individuals: N >= 0 individuals (:func:`~nsd.synth.body.make_individual`).
        poses: one unbatched :class:`~nsd.synth.body.Pose` per individual.
        cameras: the cameras, or a prepared :class:`~nsd.synth.raycast.ViewRays`
            (reuse it across frames: rays and backdrop are computed once).
        image_size: (width, height); see :func:`~nsd.synth.raycast.camera_rays`.
        background: composite over the backdrop (True) or over black (False,
            as NeTePu's masked training images).
        supersample: odd samples per pixel side for the RGB image (ground-truth
            maps always come from the pixel-centre sample); a prepared
            ``ViewRays`` brings its own.
        backdrop, light: the static world and its light.

    Returns:
        A dict (see the module docstring for conventions):

        * ``rgb``: (V, H, W, 3) float32 in [0, 1].
        * ``background``: the backdrop alone, (V, H, W, 3) float32 (zeros
          when ``background`` is False).
        * ``albedo``: texture colour of the visible surface, (V, H, W, 3); 0 on background.
        * ``instance``: (V, H, W) int64, -1 background.
        * ``part``: primitive index within the species, (V, H, W) int64, -1 background.
        * ``depth``: camera-space Z, (V, H, W) float32, inf on background.
        * ``normal``: unit world normal, (V, H, W, 3); 0 on background.
        * ``nnopcs``: (V, H, W, 3) float32 in [0, 1]; 0 on background.
        * ``visible``, ``amodal``: (V, N, H, W) bool.
        * ``amodal_depth``: per individual alone, (V, N, H, W) float32, inf outside.
        * ``boxes``, ``amodal_boxes``: (V, N, 4) float32 ``[x0, y0, x1, y1]``.
        * ``keypoints3d``: list of N float64 (K_n, 3) world keypoints.
        * ``keypoints2d``: list of N float64 (V, K_n, 2) pixels.
        * ``keypoint_visibility``: list of N int64 (V, K_n) in {0, 1, 2}.

    Example:
        >>> from nsd.synth import make_individual, ring_rig
        >>> cow = make_individual("quadruped")
        >>> out = render_views([cow], [cow.rest_pose()], ring_rig(8, size=(64, 48))[:2])
        >>> out["rgb"].shape, out["amodal"].shape
        (torch.Size([2, 48, 64, 3]), torch.Size([2, 1, 48, 64]))
    """
    if len(poses) != len(individuals):
        raise ConfigError(f"poses: got {len(poses)} poses for {len(individuals)} individuals")
    rays = (
        cameras if isinstance(cameras, ViewRays) else camera_rays(cameras, image_size, supersample)
    )
    dtype = rays.directions.dtype
    V, Hs, Ws = rays.directions.shape[:3]
    N = len(individuals)
    bodies = []
    keypoints = []
    for ind, pose in zip(individuals, poses, strict=True):
        if pose.angles.shape != (ind.num_keypoints, 3):
            raise ConfigError(
                f"poses: individual {ind.identity} ({ind.species.name}) needs unbatched angles "
                f"({ind.num_keypoints}, 3), got {tuple(pose.angles.shape)}"
            )
        pb = ind.posed(pose.to(torch.float64))
        bodies.append((pb.centres, pb.axes, pb.radii))
        keypoints.append(pb.joints)
    E = Ellipsoids.concat(bodies, dtype)
    index, dirs = rays.flat()
    hits = cast_rays(rays.origins, index, dirs, E)

    fg = hits.owner >= 0
    albedo = torch.zeros(dirs.shape[0], 3, dtype=dtype)
    nnopcs = torch.zeros_like(albedo)
    for n, ind in enumerate(individuals):
        m = hits.owner == n
        if m.any():
            nn = nnopcs_of(ind.species, hits.part[m], hits.local[m])
            nnopcs[m] = nn
            albedo[m] = ind.texture(nn)
    shaded = lambert(albedo, hits.normal, light)
    if background:
        key = ("backdrop", backdrop, light)
        if key not in rays.cache:
            bd = backdrop.cast(rays.origins[index], dirs, light)
            rays.cache[key] = bd.rgb.view(V, Hs, Ws, 3)
        bg = rays.cache[key].reshape(-1, 3)
    else:
        bg = torch.zeros_like(shaded)
    rgb = torch.where(fg[:, None], shaded, bg).view(V, Hs, Ws, 3)
    rgb = rays.pixel_average(rgb)

    def centre(x: Tensor, *tail: int) -> Tensor:
        return rays.centre_samples(x.view(V, Hs, Ws, *tail))

    zf = rays.centre_samples(rays.z_per_distance)
    instance = centre(hits.owner)
    depth = centre(hits.distance) * zf
    amodal_depth = (centre(hits.owner_distance, N) * zf[..., None]).permute(0, 3, 1, 2)
    amodal = torch.isfinite(amodal_depth)
    visible = instance[:, None] == torch.arange(N).view(1, N, 1, 1)
    uv, vis = keypoint_visibility(individuals, keypoints, rays, E)
    return {
        "rgb": rgb,
        "background": rays.pixel_average(bg.view(V, Hs, Ws, 3)),
        "albedo": centre(albedo, 3),
        "instance": instance,
        "part": centre(hits.part),
        "depth": depth,
        "normal": centre(hits.normal, 3),
        "nnopcs": centre(nnopcs, 3),
        "visible": visible,
        "amodal": amodal,
        "amodal_depth": amodal_depth,
        "boxes": mask_boxes_xyxy(visible),
        "amodal_boxes": mask_boxes_xyxy(amodal),
        "keypoints3d": keypoints,
        "keypoints2d": uv,
        "keypoint_visibility": vis,
    }
