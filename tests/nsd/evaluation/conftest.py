"""Shared fixtures of the evaluation tests."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nsd.synth.scene import tiny_config, write_scene


@pytest.fixture(scope="session")
def world(tmp_path_factory):
    """A 3-camera synthetic scene, its ground truth as an export, and its 2D keypoints."""
    root = tmp_path_factory.mktemp("labels")
    scene = write_scene(tiny_config(image_size=[64, 64], rig={
        "kind": "ring", "count": 3, "radius": 4.0, "height": 2.0, "fov_deg": 50.0,
        "start_deg": 30.0}), root / "scene")
    coco = json.loads((scene / "gt" / "coco.json").read_text())
    images = {im["id"]: im for im in coco["images"]}
    points = {}  # (camera, frame) -> identity -> (K, 2), only visible keypoints
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        a.update(camera=im["camera"], frame=im["frame"], subject_id=a["identity_id"] + 1)
        kp = np.asarray(a["keypoints"], np.float64).reshape(-1, 3)
        xy = np.where((kp[:, 2] == 2)[:, None], kp[:, :2], np.nan)
        points.setdefault((im["camera"], im["frame"]), {})[f"id{a['identity_id']}"] = xy
    export = root / "export"
    export.mkdir()
    (export / "subjects.coco.json").write_text(json.dumps(coco))
    return {"root": root, "scene": scene, "coco": coco, "export": export, "points": points}
