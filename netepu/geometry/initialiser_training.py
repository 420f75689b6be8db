"""Training the learned initialiser (:mod:`netepu.geometry.initialiser`) on the synthetic world.

Data (:func:`render_bank`)
    Individuals of one species with random identities and proportions (the synthetic
    world's spread, not only the geometry model's mean body), each in a random pose
    (:func:`nsd.synth.motion.sample_pose`: gait phase, gestures, heading) at a random place,
    seen by ``cameras`` random cameras of its own: azimuth uniform, distance, height and
    field of view drawn over studio-like ranges scaled by the body radius, aimed at the body
    with a jitter. Silhouettes come from :func:`nsd.synth.render_views` at 128 x 128.

Samples (:func:`training_batch`)
    A pose and 2-8 of its cameras whose silhouette is not empty. The silhouettes are
    spoilt as the pipeline's masks are: another subject covers an ellipse of some views
    (those pixels become occluders, as the keypoints stage gives them), pieces are missed
    (removed, not marked), and the boundary is grown or shrunk by a pixel. The volume is
    built around the triangulated centroid of the spoilt silhouettes, as at run time.

Loss: the mean Euclidean distance between predicted (soft-argmax) and true keypoints, in
the volume's units, plus ``HEATMAP_WEIGHT`` x the cross-entropy of each heatmap with the
true keypoint's trilinear weights on the heatmap cells (:func:`heatmap_targets`): the
distance alone moves a flat softmax slowly (185 mm held-out after 10 minutes, against 145
with both). Adam with a cosine decay over a step or minute budget; the figures on
``heldout`` samples (drawn from poses never trained on) are MPJPE in scene units x 1000
(mm for metres).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F

from netepu.geometry.initialiser import (
    INITIALISER_FORMAT,
    InitialiserConfig,
    PoseInitialiser,
    subject_volume,
)
from netepu.geometry.inverse import triangulate_centroids
from nsd.cameras.batch import CameraBatch
from nsd.cameras.calibration import CameraRig
from nsd.core.atomic import atomic_save_torch
from nsd.ops.vectors import up_frame
from nsd.synth import make_individual, render_views, sample_pose
from nsd.synth.rigs import look_at

__all__ = ["Bank", "TrainResult", "render_bank", "train_initialiser", "training_batch"]

log = logging.getLogger(__name__)

IMAGE_SIZE = (128, 128)
HEATMAP_WEIGHT = 0.1  # the heatmaps' cross-entropy with the true keypoints' trilinear weights
BIPED_RADIUS = 0.9  # the camera ranges below are for this body radius, scaled for others


@dataclass
class Bank:
    """Rendered poses: silhouettes (P, C, H, W) bool, cameras K, R, t (P, C, ...), float64,
    true keypoints (P, K, 3) float64."""

    masks: Tensor
    K: Tensor
    R: Tensor
    t: Tensor
    keypoints: Tensor

    @cached_property
    def view_areas(self) -> Tensor:
        """Silhouette pixels of every pose and camera, (P, C)."""
        return self.masks.flatten(2).sum(-1)

    def cameras(self, p: int, views: Tensor) -> CameraBatch:
        return CameraBatch(self.K[p, views], self.R[p, views], self.t[p, views])


def render_bank(species: str, radius: float, poses: int, cameras: int, seed: int) -> Bank:
    """``poses`` random individuals in random poses, each from ``cameras`` random cameras
    (module docstring)."""
    rng = np.random.default_rng(seed)
    s = radius / BIPED_RADIUS
    masks, Ks, Rs, ts, kps = [], [], [], [], []
    for _ in range(poses):
        ind = make_individual(species, identity=int(rng.integers(0, 10_000)),
                              seed=int(rng.integers(0, 10_000)), proportion_variation=1.0)
        pos = rng.uniform(-1.5, 1.5, 2) * s
        pose = sample_pose(ind, rng, 1.0, position=pos, heading=float(rng.uniform(0, 2 * np.pi)))
        kp = ind.keypoints3d(pose).double()
        centre = kp.mean(0).numpy()
        cams = []
        for c in range(cameras):
            az = rng.uniform(0, 2 * np.pi)
            dist = rng.uniform(3.0, 7.0) * s
            eye = (centre[0] + dist * np.cos(az), centre[1] + dist * np.sin(az),
                   rng.uniform(0.4, 3.6) * s)
            target = centre + rng.normal(0, 0.25 * s, 3)
            cams.append(look_at(f"c{c}", eye, target, IMAGE_SIZE, float(rng.uniform(40, 65))))
        out = render_views([ind], [pose], CameraRig(cams), IMAGE_SIZE, background=False)
        masks.append(out["visible"][:, 0])
        Ks.append(np.stack([c.K for c in cams]))
        Rs.append(np.stack([c.R for c in cams]))
        ts.append(np.stack([c.t for c in cams]))
        kps.append(kp)
    return Bank(torch.stack(masks), torch.from_numpy(np.stack(Ks)),
                torch.from_numpy(np.stack(Rs)), torch.from_numpy(np.stack(ts)),
                torch.stack(kps))


def _ellipse(H: int, W: int, cx: float, cy: float, ax: float, ay: float) -> Tensor:
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    return ((xs - cx) / ax) ** 2 + ((ys - cy) / ay) ** 2 <= 1.0


def _spoil(mask: Tensor, rng: np.random.Generator) -> tuple[Tensor, Tensor]:
    """One view's silhouette spoilt as a pipeline mask (module docstring): (mask, occluder)."""
    H, W = mask.shape
    ys, xs = torch.nonzero(mask, as_tuple=True)
    x0, x1, y0, y1 = (float(v) for v in (xs.min(), xs.max(), ys.min(), ys.max()))
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    occ = torch.zeros_like(mask)
    m = mask.clone()
    if rng.random() < 0.35:  # another subject in front
        e = _ellipse(H, W, rng.uniform(x0, x1), rng.uniform(y0, y1),
                     rng.uniform(0.2, 0.6) * bw + 2, rng.uniform(0.2, 0.6) * bh + 2)
        occ = e
        m = m & ~e
    if rng.random() < 0.2:  # a missed piece
        e = _ellipse(H, W, rng.uniform(x0, x1), rng.uniform(y0, y1),
                     rng.uniform(0.05, 0.2) * bw + 1, rng.uniform(0.05, 0.2) * bh + 1)
        m = m & ~e
    r = rng.random()
    if r < 0.25:
        m = F.max_pool2d(m[None, None].float(), 3, 1, 1)[0, 0] > 0
    elif r < 0.4:
        m = -F.max_pool2d(-m[None, None].float(), 3, 1, 1)[0, 0] > 0
    return m, occ & ~m


def training_batch(bank: Bank, cfg: InitialiserConfig, size: int, rng: np.random.Generator,
                   poses: np.ndarray | None = None) -> tuple[Tensor, Tensor]:
    """``size`` samples (module docstring): volumes (B, 2, G, G, G) and the true keypoints in
    the volume's frame and units (B, K, 3)."""
    basis = up_frame(torch.tensor(cfg.up, dtype=torch.float64))
    vols, targets = [], []
    while len(vols) < size:
        p = int(rng.choice(poses) if poses is not None else rng.integers(len(bank.masks)))
        valid = torch.nonzero(bank.view_areas[p] >= 16)[:, 0].numpy()
        if len(valid) < 2:
            continue
        n = int(rng.integers(2, min(8, len(valid)) + 1))
        views = torch.from_numpy(rng.choice(valid, n, replace=False))
        spoilt = [_spoil(bank.masks[p, v], rng) for v in views.tolist()]
        masks = torch.stack([m for m, _ in spoilt])
        keep = masks.flatten(1).any(1)
        if int(keep.sum()) < 2:
            continue
        masks, occ, views = masks[keep], torch.stack([o for _, o in spoilt])[keep], views[keep]
        cams = bank.cameras(p, views)
        anchor = triangulate_centroids(masks, cams)
        vols.append(subject_volume(masks, occ, cams, anchor, cfg))
        targets.append(((bank.keypoints[p] - anchor) @ basis / (cfg.extent * cfg.radius)).float())
    return torch.stack(vols), torch.stack(targets)


def heatmap_targets(points: Tensor, n: int) -> Tensor:
    """Trilinear weights of points on the centres of an n^3 grid over [-1, 1]^3 (the heatmap
    cells of :class:`~netepu.geometry.initialiser.PoseInitialiser`), points outside clamped
    to the outer cells.

    Shape:
        (..., 3) -> (..., n^3), each row summing to 1.
    """
    f = ((points + 1) * (n / 2) - 0.5).clamp(0, n - 1)
    i0 = f.floor().clamp(max=n - 2)
    w1 = f - i0
    i0 = i0.long()
    out = torch.zeros(*points.shape[:-1], n ** 3, dtype=points.dtype)
    for corner in range(8):
        bits = [(corner >> d) & 1 for d in range(3)]
        idx = torch.zeros(points.shape[:-1], dtype=torch.long)
        weight = torch.ones(points.shape[:-1], dtype=points.dtype)
        for d, b in enumerate(bits):
            idx = idx * n + i0[..., d] + b
            weight = weight * (w1[..., d] if b else 1 - w1[..., d])
        out.scatter_add_(-1, idx[..., None], weight[..., None])
    return out


@dataclass
class TrainResult:
    """steps, minutes, final training loss and held-out MPJPE (scene units x 1000): mean and
    median over keypoints and samples."""

    steps: int
    minutes: float
    loss: float
    heldout_mean: float
    heldout_median: float


def _heldout(net: PoseInitialiser, data: tuple[Tensor, Tensor]) -> tuple[float, float]:
    net.eval()
    with torch.no_grad():
        err = (net(data[0]) - data[1]).norm(dim=-1) * (net.cfg.extent * net.cfg.radius) * 1000
    net.train()
    per_sample = err.mean(1)
    return float(per_sample.mean()), float(per_sample.median())


def train_initialiser(bank: Bank, cfg: InitialiserConfig, minutes: float, out: str,
                      seed: int = 0, batch: int = 32, lr: float = 2e-3,
                      heldout: int = 256, max_steps: int = 0) -> TrainResult:
    """Train on all but the last ``heldout`` poses of ``bank`` for ``minutes`` (or
    ``max_steps``), write the checkpoint to ``out`` atomically (module docstring)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    P = len(bank.masks)
    train_poses, test_poses = np.arange(P - heldout), np.arange(P - heldout, P)
    test = training_batch(bank, cfg, heldout, np.random.default_rng(seed + 1), test_poses)
    net = PoseInitialiser(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    budget = minutes * 60.0
    start, step, loss_avg = time.perf_counter(), 0, float("nan")
    while True:
        elapsed = time.perf_counter() - start
        if (max_steps and step >= max_steps) or (not max_steps and elapsed >= budget):
            break
        progress = step / max_steps if max_steps else elapsed / budget
        for g in opt.param_groups:
            g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))
        vol, target = training_batch(bank, cfg, batch, rng, train_poses)
        logits = net.heatmap_logits(vol)
        coords = torch.softmax(logits, -1) @ net.cells
        cross_entropy = -(heatmap_targets(target, cfg.grid // 2)
                          * torch.log_softmax(logits, -1)).sum(-1).mean()
        loss = (coords - target).norm(dim=-1).mean() + HEATMAP_WEIGHT * cross_entropy
        opt.zero_grad()
        loss.backward()
        opt.step()
        value = float(loss.detach())
        loss_avg = value if step == 0 else 0.98 * loss_avg + 0.02 * value
        step += 1
        if step % 200 == 0:
            mean, median = _heldout(net, test)
            log.info("initialiser step %d (%.1f min): loss %.4f, held-out MPJPE %.1f / %.1f",
                     step, (time.perf_counter() - start) / 60, loss_avg, mean, median)
    mean, median = _heldout(net, test)
    took = (time.perf_counter() - start) / 60
    # no wall time in the file (the caller records it): the same recipe gives the same bytes
    atomic_save_torch({"format": INITIALISER_FORMAT, "config": cfg.to_dict(),
                       "state": net.state_dict(),
                       "trained": {"steps": step, "seed": seed,
                                   "batch": batch, "lr": lr,
                                   "heldout_mpjpe_mean": round(mean, 1),
                                   "heldout_mpjpe_median": round(median, 1)}}, out)
    return TrainResult(step, took, loss_avg, mean, median)
