"""An export's masks at native resolution against the ground truth
(nsd/evaluation/export_masks.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from nsd.evaluation.export_masks import boundary_f, export_mask_scores


def test_export_mask_scores_at_native_resolution(world, tmp_path):
    """The ground truth as an export scores 1; masks shifted by 3 pixels score the IoU and
    boundary F computed here by hand; a missing row scores 0 for its instance."""
    assert export_mask_scores(world["export"], world["scene"])["native_miou"] == 1.0
    coco = json.loads(json.dumps(world["coco"]))
    ious, bfs = [], []
    for a in coco["annotations"]:
        m = mask_utils.decode(a["segmentation"]).astype(bool)
        shifted = np.roll(m, 3, axis=1)
        rle = mask_utils.encode(np.asfortranarray(shifted.astype(np.uint8)))
        a["segmentation"] = dict(rle, counts=rle["counts"].decode())
        if m.sum() >= 16:
            ious.append((m & shifted).sum() / (m | shifted).sum())
            bfs.append(boundary_f(m, shifted))
    out = tmp_path / "shifted"
    out.mkdir()
    (out / "subjects.coco.json").write_text(json.dumps(coco))
    got = export_mask_scores(out, world["scene"])
    assert got["native_instances"] == len(ious)
    assert got["native_miou"] == pytest.approx(np.mean(ious), abs=0.02)  # Hungarian may swap
    assert got["native_boundary_f"] < 1.0
    coco["annotations"] = coco["annotations"][1:]
    (out / "subjects.coco.json").write_text(json.dumps(coco))
    assert export_mask_scores(out, world["scene"])["native_miou"] < got["native_miou"]


def test_union_iou_ignores_who_owns_a_pixel(world, tmp_path):
    """One mask holding every subject of its camera-frame: the union IoU stays 1 while the
    mIoU drops; an empty export scores union IoU 0."""
    coco = json.loads(json.dumps(world["coco"]))
    by_image: dict[int, list[dict]] = {}
    for a in coco["annotations"]:
        by_image.setdefault(a["image_id"], []).append(a)
    assert any(len(rows) >= 2 for rows in by_image.values())
    for rows in by_image.values():
        union = np.any([mask_utils.decode(a["segmentation"]) for a in rows], axis=0)
        rle = mask_utils.encode(np.asfortranarray(union.astype(np.uint8)))
        rows[0]["segmentation"] = dict(rle, counts=rle["counts"].decode())
    coco["annotations"] = [rows[0] for rows in by_image.values()]
    out = tmp_path / "merged"
    out.mkdir()
    (out / "subjects.coco.json").write_text(json.dumps(coco))
    got = export_mask_scores(out, world["scene"])
    assert got["native_union_iou"] == pytest.approx(1.0)
    assert got["native_miou"] < 0.9
    coco["annotations"] = []
    (out / "subjects.coco.json").write_text(json.dumps(coco))
    assert export_mask_scores(out, world["scene"])["native_union_iou"] == 0.0
