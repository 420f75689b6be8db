"""Decomposition metrics: known values, Hungarian matching, COCO AP of ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.evaluation.decomposition import coco_ap, fg_ari, score_frame
from nsd.inference.single import associate_views
from nsd.io.coco_results import encode_rle
from nsd.ops.boxes import box_iou_xywh, mask_boxes_xywh, mask_iou, match


def _rect(H, W, x0, y0, x1, y1):
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_mask_and_box_iou_known_values():
    a = _rect(10, 10, 0, 0, 4, 4)
    b = _rect(10, 10, 2, 0, 6, 4)
    assert mask_iou(a[None], b[None])[0, 0] == pytest.approx(8 / 24)
    assert box_iou_xywh(np.array([[0, 0, 4, 4]]), np.array([[2, 0, 4, 4]]))[0, 0] == pytest.approx(
        8 / 24
    )
    assert box_iou_xywh(np.array([[0, 0, 1, 1]]), np.array([[5, 5, 1, 1]]))[0, 0] == 0.0


def test_match_is_hungarian():
    iou = np.array([[0.9, 0.8], [0.85, 0.0]])  # greedy would take (0,0) and leave 1 unmatched
    assert sorted(match(iou)) == [(0, 1), (1, 0)]


def test_mask_boxes():
    m = torch.zeros(2, 8, 8, dtype=torch.bool)
    m[0, 2:5, 3:7] = True
    assert mask_boxes_xywh(m).tolist() == [[3, 2, 4, 3], [0, 0, 0, 0]]


def test_fg_ari():
    gt = np.array([[-1, 0, 0, 1, 1]])
    assert fg_ari(gt, np.array([[5, 7, 7, 3, 3]])) == pytest.approx(1.0)  # labels permuted
    assert fg_ari(gt, np.array([[0, 0, 0, 0, 0]])) == pytest.approx(0.0)


def test_score_frame_perfect_and_depth_order():
    H = W = 20
    a = _rect(H, W, 2, 2, 10, 18)  # front subject
    b_amodal = _rect(H, W, 6, 2, 14, 18)
    b_vis = b_amodal & ~a
    gt_vis = np.stack([a, b_vis])
    gt_amo = np.stack([a, b_amodal])
    gt_boxes = np.array([[2, 2, 8, 16], [10, 2, 4, 16]], float)
    pred = gt_vis.astype(float)
    good = score_frame(
        pred, np.array([0.0, 1.0]), np.ones(2, bool), gt_vis, gt_amo, gt_boxes, [7, 9]
    )
    assert good.detected == 2 and good.iou_sum == pytest.approx(2.0)
    assert good.order_total == 1 and good.order_correct == 1
    assert good.matches == {7: 0, 9: 1}
    assert good.ari == [pytest.approx(1.0)]
    bad = score_frame(
        pred, np.array([1.0, 0.0]), np.ones(2, bool), gt_vis, gt_amo, gt_boxes, [7, 9]
    )
    assert bad.order_correct == 0
    missing = score_frame(
        pred[:1], np.array([0.0]), np.ones(1, bool), gt_vis, gt_amo, gt_boxes, [7, 9]
    )
    assert missing.detected == 1 and missing.order_total == 0


def test_mask_detection_is_stricter_than_box_detection():
    """A ring inside the GT's box has the GT's box (box IoU 1, detected by box): at half
    the GT's pixels it is detected by mask too (IoU 0.5 counts), two pixels fewer and it is
    not. The GT's own mask is detected by both."""
    H = W = 20
    gt = _rect(H, W, 2, 2, 14, 18)  # 12 x 16 = 192 px
    outline = gt & ~_rect(H, W, 4, 4, 12, 16)  # 192 - 8 * 12 = 96 px, box 12 x 16
    args = (gt[None], gt[None], np.array([[2, 2, 12, 16]], float), [3])
    hollow = score_frame(outline[None].astype(float), np.zeros(1), np.ones(1, bool), *args)
    assert hollow.iou_sum == pytest.approx(96 / 192)
    assert (hollow.detected, hollow.mask_detected) == (1, 1)  # IoU exactly 0.5 counts
    thin = outline.copy()
    thin[8:10, 2] = False  # 94 px; the box is unchanged
    s = score_frame(thin[None].astype(float), np.zeros(1), np.ones(1, bool), *args)
    assert s.iou_sum < 0.5 and (s.detected, s.mask_detected) == (1, 0)
    full = score_frame(gt[None].astype(float), np.zeros(1), np.ones(1, bool), *args)
    assert (full.detected, full.mask_detected) == (1, 1)


def test_merge_rate_and_overlap_ownership():
    """One window covering both subjects is a merge; the overlap's visible pixels are
    owned by the front subject's window, and a blend that gives them to the back
    window loses exactly those pixels."""
    H = W = 20
    a = _rect(H, W, 2, 2, 10, 18)  # front, columns 2..9, 128 px
    b_amodal = _rect(H, W, 6, 2, 14, 18)  # columns 6..13, overlap columns 6..9 (64 px)
    gt_vis, gt_amo = np.stack([a, b_amodal & ~a]), np.stack([a, b_amodal])
    boxes = np.array([[2, 2, 8, 16], [10, 2, 4, 16]], float)
    args = (gt_vis, gt_amo, boxes, [7, 9])
    good = score_frame(gt_vis.astype(float), np.array([0.0, 1.0]), np.ones(2, bool), *args)
    assert (good.multi, good.merged) == (1, 0)
    assert (good.overlap_pixels, good.overlap_owned) == (64, 64)
    union = (a | b_amodal).astype(float)
    merged = score_frame(np.stack([union, np.zeros((H, W))]), np.zeros(2), np.ones(2, bool), *args)
    assert merged.merged == 1
    blended = gt_vis.astype(float) * 0.9
    blended[1][2:16, 6:10] = 1.0  # the back window claims 56 of the 64 overlap pixels
    s = score_frame(blended, np.array([0.0, 1.0]), np.ones(2, bool), *args)
    assert s.overlap_pixels == 64 and s.overlap_owned == 8 and s.merged == 0
    alone = score_frame(
        gt_vis[:1].astype(float),
        np.zeros(1),
        np.ones(1, bool),
        *[x[:1] for x in (gt_vis, gt_amo, boxes)],
        [7],
    )
    assert (alone.multi, alone.overlap_pixels) == (0, 0)


@pytest.mark.parametrize("species", [("biped", "quadruped"), ("quadruped",)])
def test_coco_ap_of_ground_truth_is_one(species):
    """Class-agnostic: the subjects' results (category 1) score against any species' ground
    truth, also a scene of quadrupeds alone (category 2; it scored AP 0 until 2026-12-01)."""
    from pycocotools.coco import COCO

    ids = {"biped": 1, "quadruped": 2}
    masks = [_rect(32, 32, 2, 2, 12, 20), _rect(32, 32, 15, 5, 30, 30)]
    gt = COCO()
    gt.dataset = {
        "images": [{"id": 1, "width": 32, "height": 32}],
        "categories": [{"id": ids[s], "name": s} for s in species],
        "annotations": [
            {
                "id": k + 1,
                "image_id": 1,
                "category_id": ids[species[k % len(species)]],
                "segmentation": encode_rle(m),
                "area": float(m.sum()),
                "bbox": [float(v) for v in mask_boxes_xywh(torch.as_tensor(m))],
                "iscrowd": 0,
            }
            for k, m in enumerate(masks)
        ],
    }
    gt.createIndex()
    res = [
        {
            "image_id": 1,
            "category_id": 1,
            "segmentation": a["segmentation"],
            "bbox": a["bbox"],
            "score": 0.9,
        }
        for a in gt.dataset["annotations"]
    ]
    ap = coco_ap(gt, res, [1])
    assert ap["coco_segm_ap"] == pytest.approx(1.0) and ap["coco_bbox_ap"] == pytest.approx(1.0)
    shifted = [{**r, "bbox": [r["bbox"][0] + 6, *r["bbox"][1:]]} for r in res]
    assert coco_ap(gt, shifted, [1])["coco_bbox_ap"] < 0.5


def test_associate_views_hungarian():
    g = torch.Generator().manual_seed(0)
    app0 = torch.randn(3, 32, generator=g)
    app = torch.stack([app0, app0[[2, 0, 1]], app0[[1, 2, 0]]])
    active = torch.ones(3, 3, dtype=torch.bool)
    ids = associate_views(app, active)
    assert ids[0].tolist() == [0, 1, 2]
    assert ids[1].tolist() == [2, 0, 1] and ids[2].tolist() == [1, 2, 0]
    active[1, 0] = False
    assert associate_views(app, active)[1, 0] == -1


def test_associate_views_references_the_view_with_most_subjects():
    """A view showing fewer subjects than another does not open new identities for the
    others' extra windows: every frame gets as many ids as its fullest view."""
    g = torch.Generator().manual_seed(1)
    app0 = torch.randn(4, 32, generator=g)
    app = torch.stack([app0, app0[[3, 1, 0, 2]], app0[[2, 3, 1, 0]]])
    active = torch.ones(3, 4, dtype=torch.bool)
    active[0, 3] = False  # the first view misses subject 3
    active[2, 0] = False  # the last view misses subject 2 (its window 0)
    ids = associate_views(app, active)
    assert len(set(ids[ids >= 0].tolist())) == 4
    subject = torch.stack([torch.arange(4), torch.tensor([3, 1, 0, 2]), torch.tensor([2, 3, 1, 0])])
    for v in range(3):  # one id per true subject, the same in every view
        for n in range(4):
            if active[v, n]:
                partners = ids[subject == subject[v, n]]
                assert set(partners[partners >= 0].tolist()) == {ids[v, n]}
    assert (associate_views(app, torch.zeros(3, 4, dtype=torch.bool)) == -1).all()
