"""Visible masks at native resolution (nsd/cues/native.py)."""

from __future__ import annotations

import cv2
import numpy as np

from nsd.cues.native import native_masks
from nsd.io.coco_results import resize_mask


def _scene(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two subjects at ``size`` x ``size``: a disc and a bar with a thin diagonal limb; the
    frame (RGB uint8), its background and the true masks (2, size, size)."""
    s = size / 64
    truth = np.zeros((2, size, size), np.uint8)
    cv2.circle(truth[0], (int(18 * s), int(30 * s)), int(10 * s), 1, -1)
    cv2.rectangle(truth[1], (int(38 * s), int(14 * s)), (int(50 * s), int(50 * s)), 1, -1)
    cv2.line(truth[1], (int(50 * s), int(20 * s)), (int(62 * s), int(4 * s)), 1,
             max(1, int(1.5 * s)))
    background = np.full((size, size, 3), 60, np.uint8)
    view = background.copy()
    view[truth[0] > 0] = (200, 40, 40)
    view[truth[1] > 0] = (40, 200, 60)
    return view, background, truth.astype(bool)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_equal_resolution_gives_back_the_masks():
    view, background, truth = _scene(64)
    got = native_masks(truth.astype(np.float32), view, background)
    assert np.array_equal(got, truth)


def test_native_masks_recover_what_upsampling_loses():
    """Masks decided at 16 x 16, frames at 128 x 128: the native masks follow the true
    boundaries and the thin limb; upsampled training-size masks do not."""
    view, background, truth = _scene(128)
    low = np.stack([cv2.resize(t.astype(np.float32), (16, 16), interpolation=cv2.INTER_AREA)
                    for t in truth]) > 0.5
    got = native_masks(low.astype(np.float32), view, background)
    upsampled = np.stack([resize_mask(m.astype(np.float32), (128, 128)) > 0.5 for m in low])
    for k in range(2):
        assert _iou(got[k], truth[k]) > 0.97
        assert _iou(got[k], truth[k]) > _iou(upsampled[k], truth[k]) + 0.05
    assert not (got[0] & got[1]).any()  # disjoint
    assert native_masks(np.zeros((0, 16, 16), np.float32), view, background).shape == (
        0, 128, 128)
