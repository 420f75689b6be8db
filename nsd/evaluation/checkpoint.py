"""Metrics of a trained decomposition checkpoint on a scene, and their Markdown table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nsd.core.errors import ConfigError, FootageError
from nsd.evaluation.decomposition import evaluate_model
from nsd.io.ground_truth import GroundTruth
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.model.checkpoint import load_decomposition

__all__ = ["METRICS", "evaluate_checkpoint", "markdown_table"]


METRICS = [
    ("detection_rate", "detection rate (IoU >= 0.5)"),
    ("mask_miou", "visible-mask mIoU"),
    ("mask_miou_raw", "visible-mask mIoU, raw compositor masks"),
    ("fg_ari", "foreground ARI"),
    ("depth_order_accuracy", "depth-order accuracy (overlapping pairs)"),
    ("association_accuracy", "cross-view association accuracy"),
    ("nvs_psnr", "novel-view PSNR (dB)"),
    ("nvs_ssim", "novel-view SSIM"),
    ("coco_bbox_ap", "COCO bbox AP"),
    ("coco_segm_ap", "COCO segm AP"),
    ("coco_segm_ap50", "COCO segm AP50"),
    ("tracking_mota", "MOTA, per-camera tracks (with export=)"),
    ("tracking_idf1", "IDF1, per-camera tracks (with export=)"),
    ("tracking_id_switches", "ID switches, per-camera tracks (with export=)"),
]


def markdown_table(metrics: dict[str, float]) -> str:
    rows = ["| metric | value |", "|---|---|"]
    for key, label in METRICS:
        if key in metrics:
            v = metrics[key]
            rows.append(f"| {label} | {'n/a' if v is None or math.isnan(v) else f'{v:.4g}'} |")
    return "\n".join(rows) + "\n"


def evaluate_checkpoint(checkpoint: str | Path, scene: str | Path | None = None,
                        frames: str | list[int] = "val", max_frames: int = 0,
                        refine: str = "residual", inference=None) -> dict[str, float]:
    """Evaluate a checkpoint on a scene (default: its training scene).

    ``inference``: :class:`nsd.inference.multiview.InferenceSettings` (None: the defaults).
    """
    trained = load_decomposition(checkpoint)
    scene = Path(scene) if scene else Path(trained.config.data.scene or "")
    if not scene or str(scene) in ("", "."):
        scene = resolve_scene(None)
    if not GroundTruth.exists(scene):
        raise FootageError(
            f"{scene} has no ground-truth masks (gt/scene.json and gt/dense/): nsd-eval needs a "
            "synthetic scene written with dense=true")
    H, W = trained.frame_hw
    cfg = trained.config
    data = SceneData(scene, (W, H), cfg.data.cameras, cfg.data.val_fraction, cfg.data.max_frames)
    trained.check_cameras(data.rig.names, scene)
    if frames == "val":
        idx = np.asarray(data.heldout_frames)
    elif frames == "all":
        idx = np.arange(len(data.frames))
    elif isinstance(frames, (list, tuple)) or hasattr(frames, "__iter__"):
        idx = np.asarray(list(frames), dtype=int)
    else:
        raise ConfigError(f"frames must be 'val', 'all' or a list of indices, got {frames!r}")
    if max_frames and len(idx) > max_frames:
        idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(int)]
    gt = GroundTruth.load(scene)
    metrics = evaluate_model(trained.model, data, idx, gt, refine=refine, inference=inference)
    metrics.update({"frames": float(len(idx)), "step": float(trained.step)})
    return metrics
