"""Streamed COCO files load with pycocotools and keep every entry in order."""

from __future__ import annotations

import json

from pycocotools.coco import COCO

from nsd.io.coco import CocoStreamWriter
from nsd.io.coco_results import encode_rle


def test_streamed_file_loads_with_pycocotools(tmp_path):
    import numpy as np

    w = CocoStreamWriter(tmp_path / "s.coco.json")
    for i in (1, 2):
        w.add_image({"id": i, "file_name": f"{i}.png", "width": 4, "height": 3})
    m = np.zeros((3, 4), bool)
    m[1, 1:3] = True
    ids = [
        w.add_annotation(
            {
                "image_id": 2,
                "category_id": 1,
                "segmentation": encode_rle(m),
                "area": 2.0,
                "bbox": [1, 1, 2, 1],
                "iscrowd": 0,
            }
        )
        for _ in range(3)
    ]
    w.close({"description": "t"}, [{"id": 1, "name": "subject"}])
    assert ids == [1, 2, 3]
    coco = COCO(str(tmp_path / "s.coco.json"))
    assert sorted(coco.getImgIds()) == [1, 2] and coco.getAnnIds(imgIds=[2]) == [1, 2, 3]
    assert (coco.annToMask(coco.anns[2]) == m).all()
    assert json.loads((tmp_path / "s.coco.json").read_text())["info"] == {"description": "t"}
    assert [p.name for p in tmp_path.iterdir()] == ["s.coco.json"]  # parts removed


def test_empty_file_is_valid(tmp_path):
    w = CocoStreamWriter(tmp_path / "e.json")
    w.close({}, [])
    d = json.loads((tmp_path / "e.json").read_text())
    assert d["images"] == [] and d["annotations"] == []
