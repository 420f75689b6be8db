"""Shared fixtures: the checked-in tiny scene, random cameras and a synthetic world."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from nsd.cameras.calibration import Camera
from nsd.synth.scene import tiny_config, write_scene

FIXTURES = Path(__file__).parent / "fixtures"

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


@pytest.fixture
def tiny_scene(tmp_path: Path) -> Path:
    """A writable copy of ``tests/fixtures/tiny_scene`` (2 views x 4 frames, 32x24)."""
    dst = tmp_path / "tiny_scene"
    shutil.copytree(FIXTURES / "tiny_scene", dst)
    return dst


def look_at_camera(
    name: str,
    center: np.ndarray,
    target: np.ndarray | None = None,
    f: float = 300.0,
    size: tuple[int, int] = (320, 240),
    dist: np.ndarray | None = None,
) -> Camera:
    """A camera at ``center`` looking at ``target`` with world z up."""
    z = (np.zeros(3) if target is None else target) - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[f, 0, size[0] / 2 - 0.5], [0, f, size[1] / 2 - 0.5], [0, 0, 1]])
    return Camera(name, K, np.zeros(5) if dist is None else dist, R, -R @ center, size)


@pytest.fixture
def random_cameras() -> list[Camera]:
    """Six cameras on a ring, with various distortions."""
    rng = np.random.default_rng(1)
    dists = [
        np.zeros(0),
        np.array([-0.2, 0.05, 0.001, -0.002]),
        np.array([-0.1, 0.02, 0.0005, 0.001, -0.003]),
        np.array([0.05, -0.01, 0.0, 0.0, 0.001, 0.01, -0.002, 0.0005]),
        np.zeros(5),
        np.array([-0.3, 0.1, 0.0, 0.0, -0.02]),
    ]
    cams = []
    for i, d in enumerate(dists):
        a = 2 * np.pi * i / len(dists)
        c = np.array([5 * np.cos(a), 5 * np.sin(a), 1.5 + rng.uniform(-0.5, 0.5)])
        cams.append(
            look_at_camera(f"cam{i}", c, rng.uniform(-0.3, 0.3, 3), f=rng.uniform(200, 400), dist=d)
        )
    return cams


def write_video(path: Path, frames: np.ndarray, fps: float = 10.0) -> Path:
    """Write RGB uint8 frames (T, H, W, 3) as an MJPG .avi (lossy but widely readable)."""
    h, w = frames.shape[1:3]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


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
