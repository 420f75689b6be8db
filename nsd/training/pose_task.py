"""NSD stage 3: a pose regressor P on the frozen decomposition, from few 3D labels.

B and E are frozen (their windows and latent clouds are computed once); P maps
a window's latent cloud, expressed in its camera's frame, to the individual's
root-relative 3D keypoints in that camera frame. Only ``pose.label_fraction``
of the training frames carry labels (or, with ``pose.labels``, a user's 3D labels, e.g.
anipose's ``pose-3d`` CSV (:mod:`nsd.io.labels`): the training frames it labels train P,
the held-out ones it labels score it); a labelled individual is tied to the
window whose visible mask holds most of its projected keypoints (labels plus
calibration only, no masks). The metric is MPJPE (root-relative, in scene
units x 1000, i.e. mm for metric scenes) on held-out frames, as NSD's Fig. 8.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor, nn

from nsd.core.device import move
from nsd.core.errors import ConfigError
from nsd.core.trainer import load_checkpoint
from nsd.evaluation.pose import mpjpe
from nsd.inference.multiview import InferenceSettings, decompose_views, model_scene_track
from nsd.model.build import build_model
from nsd.model.pose_regressor import PoseRegressor

__all__ = ["PoseTask", "label_frames"]

ROOT = 0  # keypoint index of the root (pelvis / withers) in both species


def label_frames(train_frames: np.ndarray, fraction: float, seed: int = 0) -> np.ndarray:
    """The labelled subset of training frames (at least one)."""
    if not 0 < fraction <= 1:
        raise ConfigError(f"pose.label_fraction must be in (0, 1], got {fraction}")
    rng = np.random.default_rng(seed)
    n = max(1, round(len(train_frames) * fraction))
    return np.sort(rng.choice(train_frames, size=n, replace=False))


class PoseTask:
    """Stage 3 (implements nsd.core.trainer.TrainTask)."""

    def __init__(self, cfg, data, gt, device: torch.device | None = None) -> None:
        if gt is None:
            raise ConfigError("stage=pose needs 3D keypoints: a scene with ground truth (gt/) "
                              "or pose.labels=<anipose pose-3d CSV>")
        if not cfg.init_from:
            raise ConfigError("stage=pose needs init_from=<decomposition checkpoint.pt>")
        self.cfg, self.data, self.gt = cfg, data, gt
        self.device = torch.device("cpu") if device is None else device
        if cfg.model.num_windows == "auto":  # the decomposition's windows, as it was trained
            trained = (load_checkpoint(cfg.init_from).get("config") or {}).get("model", {})
            if not isinstance(trained.get("num_windows"), int):
                raise ConfigError(f"init_from={cfg.init_from} does not say its windows: give "
                                  "model.num_windows (the decomposition's)")
            cfg.model.num_windows = trained["num_windows"]
        self.model = build_model(cfg.model).to(self.device)
        for p in self.model.parameters():
            p.requires_grad_(False)
        if hasattr(gt, "frames"):  # a user's labels: every labelled training frame
            labelled = set(gt.frames.tolist())  # footage frames; data indices are positions

            def on(ts: np.ndarray) -> np.ndarray:
                return np.array([t for t in ts if data.frame_index(t) in labelled], int)

            self.labelled = on(data.train_frames)
            missing = [n for n, f in (("training", self.labelled),
                                      ("held-out", on(data.heldout_frames))) if not len(f)]
            if missing:
                raise ConfigError(
                    f"pose.labels {gt.source}: no labelled {' or '.join(missing)} frames "
                    f"(labelled: {len(gt.frames)} frames; the held-out tail is the last "
                    f"data.val_fraction of the footage)")
        else:
            self.labelled = label_frames(data.train_frames, cfg.pose.label_fraction,
                                         cfg.trainer.seed)
        self._latents: dict[str, tuple[Tensor, Tensor]] = {}
        self.regressor: PoseRegressor | None = None
        self.opt: torch.optim.Optimizer | None = None
        self._build_regressor()

    def _build_regressor(self) -> None:
        K = self.gt.num_keypoints
        self.regressor = PoseRegressor(
            self.model.encoder.points, K, self.cfg.pose.hidden, self.cfg.pose.dropout
        ).to(self.device)
        self.opt = torch.optim.Adam(self.regressor.parameters(), lr=self.cfg.pose.lr)

    # ------------------------------------------------------------------ samples
    @torch.no_grad()
    def samples(self, frames: np.ndarray) -> tuple[Tensor, Tensor]:
        """Latent clouds (S, P, 3) and root-relative camera-frame keypoints (S, K, 3)."""
        latents, targets = [], []
        rig = self.data.rig
        settings = InferenceSettings.from_config(self.cfg.get("inference")).for_views(len(rig))
        grid = settings.grid(rig, self.data.frame_hw) if settings.multiview else None
        track = (None if grid is None else  # the hull's clustering through the frames
                 model_scene_track(self.model, self.data.views, frames, grid, settings.mixture))
        for t in frames:
            views, bgs = self.data.views(int(t))
            dec = decompose_views(self.model, views, bgs, len(rig), settings, grid, track=track)
            kp = self.gt.keypoints3d(self.data.frame_index(t))  # identity -> (K, 3) world
            for v, cam in enumerate(rig):
                act = np.flatnonzero(dec.active[v].numpy())
                ids = list(kp)
                if not len(act) or not ids:
                    continue
                counts = np.zeros((len(act), len(ids)))
                masks = dec.masks[v, act].numpy() > 0.5
                H, W = masks.shape[-2:]
                for g, ident in enumerate(ids):
                    uv, z = cam.project(kp[ident])
                    ok = (
                        (z > 0)
                        & (uv[:, 0] >= 0)
                        & (uv[:, 0] < W)
                        & (uv[:, 1] >= 0)
                        & (uv[:, 1] < H)
                    )
                    u, w_ = uv[ok, 0].astype(int), uv[ok, 1].astype(int)
                    counts[:, g] = masks[:, w_, u].sum(1)
                rows, cols = linear_sum_assignment(-counts)
                for r, c in zip(rows, cols, strict=True):
                    if counts[r, c] < 3:
                        continue
                    X = kp[ids[c]] @ cam.R.T + cam.t
                    targets.append(torch.as_tensor(X - X[ROOT], dtype=torch.float32))
                    latents.append(dec.latent[v, act[r]])
        if not latents:
            raise ConfigError(
                "no labelled window matched a labelled individual; train the "
                "decomposition longer or raise pose.label_fraction"
            )
        return torch.stack(latents), torch.stack(targets)

    def _cached(self, name: str, frames: np.ndarray) -> tuple[Tensor, Tensor]:
        if name not in self._latents:
            self._latents[name] = move(self.samples(frames), self.device)
        return self._latents[name]

    # ------------------------------------------------------------------ TrainTask
    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model, "pose": self.regressor}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"pose": self.opt}

    def extra_state(self) -> dict[str, Any]:
        return {"labelled": torch.as_tensor(self.labelled)}

    def load_extra_state(self, state: Mapping[str, Any]) -> None:
        if "labelled" in state:
            self.labelled = state["labelled"].numpy()

    def training_step(self, step: int, rng: np.random.Generator) -> dict[str, Tensor]:
        lat, tgt = self._cached("train", self.labelled)
        idx = torch.as_tensor(rng.integers(0, len(lat), size=min(64, len(lat))), device=self.device)
        pred = self.regressor(lat[idx])
        loss = (pred - tgt[idx]).pow(2).mean()
        return {"loss": loss, "mpjpe": mpjpe(pred.detach(), tgt[idx]) * 1000}

    @torch.no_grad()
    def evaluate(self, step: int) -> dict[str, float]:
        lat, tgt = self._cached("val", self.data.heldout_frames)
        self.regressor.eval()
        err = mpjpe(self.regressor(lat), tgt).item() * 1000
        self.regressor.train()
        return {
            "mpjpe_mm": err,
            "labelled_frames": float(len(self.labelled)),
            "val_samples": float(len(lat)),
            "mask_miou": math.nan,
        }

    def image_grids(self, step: int) -> dict[str, np.ndarray]:
        return {}
