"""A tiny analytic world for NeTePu tests: balls on the keypoints of a toy skeleton.

Every keypoint carries a ball of radius ``BALL``; views are ray-cast exactly
(rays from :func:`nsd.cameras.projection.pixel_to_normalized`, so lens distortion is
honoured). Depth is the camera Z of the first hit; the "NNOPCS" of a hit is
its keypoint's fixed colour plus a small offset along the ball's surface, so
it is pose- and view-independent like the real thing.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import numpy as np
import torch

from netepu.geometry.data import DataConfig, GeometryData, ViewSet, make_point_pools
from netepu.geometry.maps import MapSettings, render_maps
from nsd.cameras.calibration import Camera, CameraRig
from nsd.cameras.projection import pixel_to_normalized
from tests.conftest import look_at_camera

BALL = 0.22  # metres
# a toy quadruped: spine of 3, head, 4 feet (K = 8)
REST = np.array(
    [
        [-0.6, 0.0, 1.0],
        [0.0, 0.0, 1.05],
        [0.6, 0.0, 1.0],
        [1.0, 0.0, 1.3],
        [-0.6, 0.25, 0.2],
        [-0.6, -0.25, 0.2],
        [0.6, 0.25, 0.2],
        [0.6, -0.25, 0.2],
    ]
)
K_TOY = len(REST)
RADIUS = 0.8


def toy_pose(rng: np.random.Generator, jitter: float = 0.08) -> np.ndarray:
    """A random pose: rest pose + joint jitter, random heading, small ground offset."""
    a = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    pts = REST + rng.normal(0, jitter, REST.shape)
    return pts @ R.T + np.array([*rng.uniform(-0.2, 0.2, 2), 0.0])


def ring(
    n: int = 6, size: tuple[int, int] = (64, 48), dist=None, radius: float = 4.5, f: float = 70.0
) -> CameraRig:
    cams = [
        look_at_camera(
            f"cam{i}",
            np.array([radius * np.cos(2 * np.pi * i / n), radius * np.sin(2 * np.pi * i / n), 1.6]),
            np.array([0.0, 0.0, 0.7]),
            f=f,
            size=size,
            dist=dist,
        )
        for i in range(n)
    ]
    return CameraRig(cams)


def render_balls(keypoints: np.ndarray, camera: Camera) -> dict[str, np.ndarray]:
    """Exact ray casting of the balls: mask (H, W), depth (H, W), nnopcs (H, W, 3)."""
    w, h = camera.size
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    uv = torch.from_numpy(np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64))
    p = camera.tensors(torch.float64)
    xy = pixel_to_normalized(uv, p["K"], p["dist"]).numpy()
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ camera.R  # world, camera Z = s
    o = camera.center
    best = np.full(len(d), np.inf)
    who = np.full(len(d), -1)
    for j, c in enumerate(keypoints):
        oc = o - c
        a = (d * d).sum(1)
        b = 2 * d @ oc
        cc = oc @ oc - BALL**2
        disc = b * b - 4 * a * cc
        s = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        closer = s < best
        best = np.where(closer, s, best)
        who = np.where(closer, j, who)
    mask = who >= 0
    colour = np.stack(
        [
            np.linspace(0.1, 0.9, K_TOY),
            np.linspace(0.9, 0.1, K_TOY) ** 2,
            (np.arange(K_TOY) % 3) / 3 + 0.15,
        ],
        1,
    )
    hit = o + d * np.where(mask, best, 0)[:, None]
    local = (hit - keypoints[np.maximum(who, 0)]) / BALL
    nnopcs = np.clip(colour[np.maximum(who, 0)] + 0.08 * local, 0, 1) * mask[:, None]
    return {
        "mask": mask.reshape(h, w),
        "depth": np.where(mask, best, 0).reshape(h, w),
        "nnopcs": nnopcs.reshape(h, w, 3),
    }


def render_views(poses: list[np.ndarray], rig: CameraRig) -> dict[str, np.ndarray]:
    out = {"mask": [], "depth": [], "nnopcs": []}
    for kp in poses:
        for cam in rig:
            r = render_balls(kp, cam)
            for k in out:
                out[k].append(r[k])
    return {k: np.stack(v) for k, v in out.items()}


def view_set(poses: list[np.ndarray], rig: CameraRig) -> ViewSet:
    maps = render_views(poses, rig)
    C = len(rig)
    cams = rig.stacked(torch.float32)
    kp = torch.from_numpy(np.stack(poses).astype(np.float32)).repeat_interleave(C, 0)
    ci = torch.arange(C).repeat(len(poses))
    return ViewSet(
        kp,
        cams[ci],
        torch.from_numpy(maps["mask"]),
        torch.from_numpy(maps["depth"]).float(),
        torch.from_numpy(maps["nnopcs"]).half(),
    )


def toy_data(
    n_poses: int = 2, rig: CameraRig | None = None, seed: int = 0, pool: int = 300
) -> GeometryData:
    """A :class:`GeometryData` of ``n_poses`` toy poses seen by ``rig`` (default 6 cameras)."""
    rng = np.random.default_rng(seed)
    rig = rig or ring()
    poses = [toy_pose(rng) for _ in range(n_poses)]
    cfg = DataConfig.defaults(
        species="toy",
        radius=RADIUS,
        image_size=rig[0].size,
        pool_near=pool,
        pool_far=pool,
        pool_foreground=pool,
        n_keypoints=K_TOY,
    )
    vs = view_set(poses, rig)
    C = len(rig)
    pools = make_point_pools(
        vs.keypoints,
        vs.camera,
        vs.mask.numpy(),
        vs.depth.numpy(),
        vs.nnopcs.numpy(),
        np.repeat(np.arange(n_poses), C),
        np.tile(np.arange(C), n_poses),
        cfg,
        rng,
    )
    held = view_set([toy_pose(rng)], rig)
    return GeometryData(
        cfg,
        torch.from_numpy(np.stack(poses).astype(np.float32)),
        rig,
        pools,
        {"train": vs, "heldout_poses": held},
    )


TINY_MODEL = {
    "encoder": {"width": 32, "latent": 64, "n_blocks": 1, "n_freq": 3},
    "decoder": {"features": 32, "bottleneck": 32, "n_blocks": 1, "k_first": 4},
    "renderer": {"width": 32, "n_blocks_2d": 1, "k_2d": 4, "k": 6, "n_freq": 3, "hidden": 16,
                 "groups": 4, "head_hidden": 32, "head_blocks": 1},
}


# the toy trainer's folder, removed when the test session's interpreter exits
_SCRATCH = tempfile.TemporaryDirectory(prefix="netepu-toy-")


@functools.cache
def trained_toy(steps: int = 300):
    """A tiny geometry model trained on one toy pose seen by 6 cameras (~5 s, once per session).

    Returns:
        ``(model, data, trainer)`` with the model in eval mode.
    """
    from netepu.geometry.losses import GeometryLossWeights
    from netepu.geometry.maps import MapSettings
    from netepu.geometry.model import build_geometry_model
    from netepu.geometry.stage import GeometryStageConfig, GeometryTask
    from nsd.core.trainer import Trainer, TrainerConfig, seed_everything

    seed_everything(0)
    data = toy_data(n_poses=1)
    model = build_geometry_model(TINY_MODEL, K_TOY, RADIUS)
    task = GeometryTask(model, data, GeometryStageConfig.defaults(
        batch_size=4, near=150, far=150, foreground=100, lr=3e-3, keypoint_noise=0.0,
        eval_views=6), GeometryLossWeights.defaults(), MapSettings.defaults())
    out = Path(_SCRATCH.name) / f"toy-{steps}"
    trainer = Trainer(task, TrainerConfig.defaults(max_steps=steps, progress=False, log_every=50,
                                          checkpoint_every=0, grad_clip=1.0), out)
    trainer.fit()
    model.eval()
    return model, data, trainer


def own_renders(model, keypoints, cam, size):
    """A geometry model's own silhouettes (V, H, W) of ``keypoints`` (K, 3) in the views
    ``cam``, and the pose's code."""
    with torch.no_grad():
        code = model.encode(keypoints[None])
        return render_maps(model.query, model.prepare(code, cam), size,
                           MapSettings.defaults()).silhouette, code
