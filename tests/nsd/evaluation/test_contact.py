"""The apart / touching split of the decomposition metrics, on hand-built cases."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nsd.evaluation.contact import pairs_in_contact, touches, touching_instants
from nsd.evaluation.decomposition import Tally, instant_truth, score_views
from nsd.io.ground_truth import FrameGT
from nsd.ops.boxes import mask_boxes_xywh

H = W = 20


def _box(y0, x0, y1, x1):
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_pairs_in_contact_need_overlap_in_most_cameras_that_see_both():
    a, b, far = _box(2, 2, 10, 10), _box(5, 5, 12, 12), _box(14, 14, 19, 19)
    views = [  # identities 1, 2, 3 in three cameras
        ([1, 2, 3], np.stack([a, b, far])),  # 1-2 overlap, 3 apart
        ([1, 2, 3], np.stack([a, b, a])),    # 1-2 overlap, 1-3 overlap (occlusion)
        ([1, 2, 3], np.stack([a, far, b])),  # 1-3 overlap
    ]
    # 1-2: 2 of 3 cameras; 1-3: 2 of 3; 2-3: 1 of 3 (not most)
    assert pairs_in_contact(views) == {(1, 2), (1, 3)}
    # a pair seen by two cameras overlapping in one: half is not most
    assert pairs_in_contact(views[1:]) == {(1, 3)}
    # below the pixel threshold an overlap does not count
    corner = _box(9, 9, 11, 11)  # overlaps a in one pixel
    assert pairs_in_contact([([1, 2], np.stack([a, corner]))] * 3) == set()
    assert pairs_in_contact([([1, 2], np.stack([a, corner]))] * 3, min_overlap=1) == {(1, 2)}


def _frame(ids, visible, amodal):
    vis = np.stack(visible)
    boxes = mask_boxes_xywh(torch.as_tensor(vis)).numpy()
    return FrameGT(vis, np.stack(amodal), boxes, np.asarray(ids), 0, (H, W))


class _GT:
    """Two cameras, two frames: frame 0 apart, frame 1 touching (overlap in both cameras)."""

    def __init__(self):
        a, b = _box(2, 2, 10, 8), _box(2, 12, 10, 18)
        b_close = _box(2, 6, 10, 12)  # amodal overlaps a by 2 columns
        b_vis = b_close & ~a
        self.frames = {0: _frame([1, 2], [a, b], [a, b]),
                       1: _frame([1, 2], [a, b_vis], [a, b_close])}

    def frame(self, cam, t, size=None):
        return self.frames[t]


def test_touching_instants_on_a_hand_built_sequence():
    assert touching_instants(_GT(), ["c0", "c1"], [0, 1]) == {0: False, 1: True}


def test_metrics_split_into_apart_and_touching_instants():
    gt = _GT()
    data = SimpleNamespace(rig=SimpleNamespace(names=["c0", "c1"]), frame_hw=(H, W),
                           frame_index=lambda t: t)
    tally = Tally()
    for t in (0, 1):
        truths = instant_truth(gt, data, t)
        f = gt.frames[t]
        # apart: both found; touching: one window swallows both (a merge)
        masks = f.visible.astype(float) if t == 0 else np.stack(
            [f.visible.any(0).astype(float), np.zeros((H, W))])
        dec = SimpleNamespace(masks=np.stack([masks] * 2), raw_masks=np.stack([masks] * 2),
                              depths=np.zeros((2, 2)), active=np.ones((2, 2), bool))
        score_views(dec, truths, 0.5, tally.counts(touches(truths)))
    m = tally.metrics()
    assert m["detection_rate_apart"] == pytest.approx(1.0)
    assert m["mask_miou_apart"] == pytest.approx(1.0)
    assert m["merge_rate_apart"] == pytest.approx(0.0)
    # touching, per camera: the merged window (80 pixels) is matched to individual 1
    # (48 pixels, IoU 0.6, box IoU 0.6: detected), the empty one to individual 2 (IoU 0)
    assert m["mask_miou_touching"] == pytest.approx(0.3)
    assert m["detection_rate_touching"] == pytest.approx(0.5)
    assert m["merge_rate_touching"] == pytest.approx(1.0)
    assert m["mask_miou"] == pytest.approx((4 * 1.0 + 2 * 0.6) / 8)
    assert m["detection_rate"] == pytest.approx(6 / 8)
    assert m["touching_share"] == pytest.approx(0.5)
