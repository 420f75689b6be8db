"""Metrics of a trained decomposition checkpoint on a scene, and their Markdown table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nsd.core.device import resolve_device
from nsd.core.errors import ConfigError, FootageError
from nsd.evaluation.contact import PARTS
from nsd.evaluation.decomposition import evaluate_model
from nsd.evaluation.hull_baseline import evaluate_hull
from nsd.inference.multiview import InferenceSettings
from nsd.io.ground_truth import GroundTruth
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.model.checkpoint import load_decomposition

__all__ = ["METRICS", "evaluate_checkpoint", "markdown_table"]


METRICS = [
    ("detection_rate", "detection rate (box IoU >= 0.5)"),
    ("mask_detection_rate", "detection rate by visible mask (mask IoU >= 0.5)"),
    ("mask_miou", "visible-mask mIoU"),
    ("mask_miou_raw", "visible-mask mIoU, raw compositor masks"),
    ("fg_ari", "foreground ARI"),
    ("depth_order_accuracy", "depth-order accuracy (overlapping pairs)"),
    ("association_accuracy", "cross-view association accuracy"),
    ("merge_rate", "merge rate (one window over two individuals)"),
    ("nvs_psnr", "novel-view PSNR (dB)"),
    ("nvs_ssim", "novel-view SSIM"),
    ("coco_bbox_ap", "COCO bbox AP"),
    ("coco_segm_ap", "COCO segm AP"),
    ("coco_segm_ap50", "COCO segm AP50"),
    ("tracking_mota", "MOTA, per-camera tracks (with export=)"),
    ("tracking_idf1", "IDF1, per-camera tracks (with export=)"),
    ("tracking_id_switches", "ID switches, per-camera tracks (with export=)"),
]


def _cell(metrics: dict[str, float], key: str) -> str:
    v = metrics.get(key)
    if key not in metrics:
        return ""
    return "n/a" if v is None or math.isnan(v) else f"{v:.4g}"


def markdown_table(metrics: dict[str, float]) -> str:
    """The metrics as a Markdown table: a column for all frames, one each for the apart and
    touching instants (:mod:`nsd.evaluation.contact`), and the same for the hull-only
    baseline (``hull_`` keys, :mod:`nsd.evaluation.hull_baseline`) when present."""
    groups = [("", "learned")] + ([("hull_", "hull-only")] if "hull_mask_miou" in metrics else [])
    head = ["metric"]
    for _, name in groups:
        head += [f"{name}, all", f"{name}, apart", f"{name}, touching"]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key, label in METRICS:
        if key not in metrics:
            continue
        cells = [label]
        for prefix, _ in groups:
            cells += [_cell(metrics, prefix + key)]
            cells += [_cell(metrics, f"{prefix}{key}_{part}") for part in PARTS]
        rows.append("| " + " | ".join(cells) + " |")
    share = metrics.get("touching_share")
    if share is not None and not math.isnan(share):
        rows.append(f"\nTouching instants: {share:.0%} of {int(metrics.get('frames', 0))} frames.")
    return "\n".join(rows) + "\n"


def evaluate_checkpoint(checkpoint: str | Path, scene: str | Path | None = None,
                        frames: str | list[int] = "val", max_frames: int = 0,
                        refine: str = "residual", inference=None,
                        baseline: bool = True, device: str = "cpu") -> dict[str, float]:
    """Evaluate a checkpoint on a scene (default: its training scene).

    ``inference``: :class:`nsd.inference.multiview.InferenceSettings` (None: the defaults).
    ``baseline``: also score the hull-only decomposition with the checkpoint's number of
    windows on the same frames (keys ``hull_<metric>``; scenes of 2 or more cameras).
    ``device``: where the model runs (a ``device`` setting, :mod:`nsd.core.device`).
    """
    trained = load_decomposition(checkpoint, resolve_device(device))
    scene = Path(scene) if scene else Path(trained.config.data.scene or "")
    if not scene or str(scene) in ("", "."):
        scene = resolve_scene(None)
    if not GroundTruth.exists(scene):
        raise FootageError(
            f"{scene} has no ground-truth masks (gt/scene.json and gt/dense/): nsd-eval needs a "
            "synthetic scene written with dense=true")
    H, W = trained.frame_hw
    cfg = trained.config
    data = SceneData(scene, (W, H), cfg.data.cameras, cfg.data.val_fraction, cfg.data.max_frames,
                     cfg.data.get("units", "auto"), cfg.data.get("frame_stride", 1),
                     cfg.data.get("background", "median"))  # as trained; older: the median
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
    if baseline and data.num_views >= 2:
        settings = inference or InferenceSettings.defaults()
        model = trained.model
        hull = evaluate_hull(data, idx, gt, settings.grid(data.rig, data.frame_hw),
                             model.cfg.num_windows, split=not model.detector.use_presence,
                             rules=settings.mixture, speckle=settings.speckle)
        metrics.update({f"hull_{k}": v for k, v in hull.items()})
    metrics.update({"frames": float(len(idx)), "step": float(trained.step)})
    return metrics
