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
