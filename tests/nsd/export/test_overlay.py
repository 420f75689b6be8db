"""Overlay videos (nsd/export/overlay.py) on the tiny scene with a hand-made export."""

from __future__ import annotations

import json

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from nsd.evaluation.visualise import PALETTE
from nsd.export.overlay import ALPHA, draw_subjects, write_overlay_videos


def _ann(aid: int, image_id: int, box: list[float], depth: float, subject: int) -> dict:
    m = np.zeros((24, 32), np.uint8)
    x, y, w, h = (int(v) for v in box)
    m[y:y + h, x:x + w] = 1
    rle = mask_utils.encode(np.asfortranarray(m))
    rle["counts"] = rle["counts"].decode()
    return {"id": aid, "image_id": image_id, "bbox": box, "segmentation": rle, "depth": depth,
            "subject_id": subject}


def test_a_mask_is_tinted_with_its_identity_colour_and_near_is_drawn_last():
    """Footage pixels (24 x 32) drawn at 4x: the far subject's tint, then the near one's on
    top where they overlap."""
    img = np.zeros((96, 128, 3), np.uint8)
    far = _ann(1, 1, [2.0, 2.0, 20.0, 20.0], depth=5.0, subject=1)
    near = _ann(2, 1, [10.0, 10.0, 10.0, 10.0], depth=2.0, subject=2)
    out = draw_subjects(img, [far, near], [3, 4], 4.0, 0)
    far_tint = (np.asarray(PALETTE[3], float) * ALPHA).astype(np.uint8)
    both = (far_tint * (1 - ALPHA) + np.asarray(PALETTE[4], float) * ALPHA).astype(np.uint8)
    np.testing.assert_array_equal(out[24, 24], far_tint)  # footage (6, 6): far only
    np.testing.assert_array_equal(out[60, 60], both)  # footage (15, 15): near over far
    assert (out[2, 126] == 0).all()  # nothing drawn outside


def test_write_overlay_videos_writes_every_exported_frame(tiny_scene, tmp_path):
    images = [{"id": i + 1, "camera": cam, "frame": t}
              for i, (cam, t) in enumerate((c, t) for c in ("left", "right") for t in (1, 3))]
    anns = [_ann(k + 1, im["id"], [4.0, 4.0, 8.0, 8.0], 3.0, 1) for k, im in enumerate(images)]
    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "subjects.coco.json").write_text(
        json.dumps({"images": images, "annotations": anns}))
    res = write_overlay_videos(tmp_path / "export", tiny_scene, tmp_path / "overlays",
                               {1: 7}, size=64)
    assert res["frames"] == {"left": 2, "right": 2} and res["codec"] in ("avc1", "mp4v")
    cap = cv2.VideoCapture(str(tmp_path / "overlays" / "left.mp4"))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        assert frame.shape == (48, 64, 3)
    assert n == 2
