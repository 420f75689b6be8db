"""An export's visible masks against the ground truth at the footage's native resolution.

``nsd-eval`` scores the decomposition at the training size; what users take away is the
export, at native resolution (upsampled or redrawn there: :mod:`nsd.cues.native`). Every
ground-truth instance with at least ``min_area`` visible pixels in an exported camera-frame
is matched one-to-one (Hungarian on mask IoU) to the export's masks of that camera-frame:

* ``native_miou``: mean IoU over the ground-truth instances (unmatched: 0);
* ``native_boundary_f``: mean F-score of the mask boundaries, a boundary pixel counting as
  found within ``tolerance`` pixels (as the DAVIS benchmark's boundary measure);
* ``native_union_iou``: mean over camera-frames of the IoU of the union of the export's
  masks with the union of the ground truth's: where the foreground is, whoever owns it
  (the mIoU's ceiling if every pixel went to the right subject).
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

__all__ = ["boundary_f", "export_mask_scores"]


def _masks(coco: dict) -> dict[tuple[str, int], list[np.ndarray]]:
    images = {im["id"]: im for im in coco["images"]}
    out: dict[tuple[str, int], list[np.ndarray]] = defaultdict(list)
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        out[(im["camera"], int(im["frame"]))].append(
            mask_utils.decode(a["segmentation"]).astype(bool))
    return out


def _edge(m: np.ndarray) -> np.ndarray:
    m8 = m.astype(np.uint8)
    return (m8 - cv2.erode(m8, np.ones((3, 3), np.uint8))) > 0


def boundary_f(truth: np.ndarray, pred: np.ndarray, tolerance: int = 2) -> float:
    """Boundary F-score of two (H, W) bool masks (1 when both are empty).

    Example:
        >>> m = np.zeros((20, 20), bool); m[5:15, 5:15] = True
        >>> boundary_f(m, m), boundary_f(m, np.roll(m, 5, axis=1), tolerance=1) < 0.7
        (1.0, True)
    """
    bt, bp = _edge(truth), _edge(pred)
    if not bt.any() and not bp.any():
        return 1.0
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance + 1, 2 * tolerance + 1))
    near_t = cv2.dilate(bt.astype(np.uint8), k) > 0
    near_p = cv2.dilate(bp.astype(np.uint8), k) > 0
    precision = (bp & near_t).sum() / max(bp.sum(), 1)
    recall = (bt & near_p).sum() / max(bt.sum(), 1)
    return float(2 * precision * recall / max(precision + recall, 1e-12))


def export_mask_scores(export: str | os.PathLike, scene: str | os.PathLike,
                       min_area: int = 16, tolerance: int = 2) -> dict[str, float]:
    """``native_miou``, ``native_boundary_f``, ``native_union_iou`` and ``native_instances``
    (module docstring)."""
    ours = json.loads((Path(export) / "subjects.coco.json").read_text())
    exported = {(im["camera"], int(im["frame"])) for im in ours["images"]}
    pred = _masks(ours)
    truth = _masks(json.loads((Path(scene) / "gt" / "coco.json").read_text()))
    ious, bfs, unions = [], [], []
    for key in sorted(exported & set(truth)):
        gts = [t for t in truth[key] if t.sum() >= min_area]
        preds = pred.get(key, [])
        if gts:
            t_all = np.any(gts, axis=0)
            p_all = np.any(preds, axis=0) if preds else np.zeros_like(t_all)
            unions.append((t_all & p_all).sum() / max((t_all | p_all).sum(), 1))
        iou = np.zeros((len(gts), len(preds)))
        for i, t in enumerate(gts):
            for j, p in enumerate(preds):
                iou[i, j] = (t & p).sum() / max((t | p).sum(), 1)
        match = dict(zip(*linear_sum_assignment(-iou), strict=True)) if iou.size else {}
        for i, t in enumerate(gts):
            j = match.get(i)
            ious.append(float(iou[i, j]) if j is not None else 0.0)
            bfs.append(boundary_f(t, preds[j], tolerance) if j is not None else 0.0)
    nan = float("nan")
    return {"native_miou": float(np.mean(ious)) if ious else nan,
            "native_boundary_f": float(np.mean(bfs)) if bfs else nan,
            "native_union_iou": float(np.mean(unions)) if unions else nan,
            "native_instances": float(len(ious))}
