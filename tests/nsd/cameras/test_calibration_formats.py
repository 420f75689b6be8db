"""The other calibration formats: round trips by projection, known values, the dispatch."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_formats import (
    read_caliscope,
    read_colmap,
    read_panoptic,
    write_caliscope,
    write_colmap,
    write_panoptic,
)
from nsd.cameras.calibration_io import (
    find_calibration,
    read_calibration,
    read_opencv_yaml,
    write_opencv_yaml,
    write_toml,
)
from nsd.core.errors import CalibrationError


def _points(n: int = 300) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1.0, 1.0, (n, 3)) * [1.0, 1.0, 1.5]


def _same_projections(a: CameraRig, b: CameraRig, atol: float = 1e-6) -> None:
    """Every camera of ``b`` projects like its namesake in ``a``, to ``atol`` pixels."""
    X = _points()
    assert b.names == a.names
    for ca, cb in zip(a, b, strict=True):
        np.testing.assert_allclose(cb.project(X)[0], ca.project(X)[0], rtol=0, atol=atol)
        assert tuple(cb.size) == tuple(ca.size)


def test_caliscope_round_trip(random_cameras, tmp_path):
    rig = CameraRig([c.__class__(f"cam_{i}", c.K, c.dist, c.R, c.t, c.size)
                     for i, c in enumerate(random_cameras)])
    write_caliscope(rig, tmp_path / "camera_array.toml")
    _same_projections(rig, read_calibration(tmp_path))


def test_caliscope_ignored_camera_is_left_out(tmp_path):
    """A camera_array.toml as caliscope writes it: [cameras.N], 3x3 rotation, extra keys."""
    table = ("size = [1280, 720]\nmatrix = [[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], "
             "[0.0, 0.0, 1.0]]\ndistortions = [-0.3, 0.1, 0.0, 0.0, 0.0]\n"
             "translation = [0.1, 0.2, 1.5]\nrotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], "
             "[0.0, 0.0, 1.0]]\nerror = 0.2\nexposure = -7\n")
    (tmp_path / "camera_array.toml").write_text(
        f"[cameras.0]\ncam_id = 0\n{table}\n[cameras.1]\ncam_id = 1\nignore = true\n{table}\n"
        f"[cameras.10]\ncam_id = 10\n{table}")
    rig = read_caliscope(tmp_path / "camera_array.toml")
    assert rig.names == ["cam_0", "cam_10"]
    np.testing.assert_allclose(rig[0].center, -np.array([0.1, 0.2, 1.5]))


def test_panoptic_round_trip_in_centimetres(random_cameras, tmp_path):
    rig = CameraRig(random_cameras)
    write_panoptic(rig, tmp_path / "calibration_seq.json")
    _same_projections(rig, read_panoptic(tmp_path / "calibration_seq.json"))
    cm = json.loads((tmp_path / "calibration_seq.json").read_text())["cameras"][0]["t"]
    np.testing.assert_allclose(np.ravel(cm), random_cameras[0].t * 100)
    _same_projections(rig, read_calibration(tmp_path))


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip(random_cameras, tmp_path, binary):
    rig = CameraRig(random_cameras)
    write_colmap(rig, tmp_path / "sparse" / "0", binary=binary)
    back = read_calibration(tmp_path)
    _same_projections(rig, back)
    np.testing.assert_allclose(np.stack([c.R for c in back]), np.stack([c.R for c in rig]),
                               atol=1e-12)


def test_colmap_text_known_values(tmp_path):
    """PINHOLE with COLMAP's pixel centres (+0.5) and a quaternion of 90 degrees about z."""
    (tmp_path / "cameras.txt").write_text(
        "# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n1 PINHOLE 640 480 500 510 320.5 240.5\n"
        "2 SIMPLE_RADIAL 640 480 400 320 240 -0.1\n")
    s = np.sqrt(0.5)
    (tmp_path / "images.txt").write_text(
        "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n"
        f"1 {s} 0 0 {s} 1 2 3 1 left/000000.png\n100.0 200.0 -1\n"
        "2 1 0 0 0 0 0 5 2 right.png\n\n")
    rig = read_colmap(tmp_path)
    assert rig.names == ["left", "right"]
    np.testing.assert_allclose(rig[0].K, [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    np.testing.assert_allclose(rig[0].R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(rig[0].t, [1, 2, 3])
    np.testing.assert_allclose(rig[1].dist, [-0.1, 0, 0, 0])


def test_colmap_fisheye_model_is_refused(tmp_path, random_cameras):
    write_colmap(CameraRig(random_cameras[:2]), tmp_path, binary=True)
    data = bytearray((tmp_path / "cameras.bin").read_bytes())
    data[12:16] = (5).to_bytes(4, "little")  # first camera's model id -> OPENCV_FISHEYE
    (tmp_path / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(CalibrationError, match="OPENCV_FISHEYE"):
        read_colmap(tmp_path)


@pytest.mark.parametrize("n", [12, 14])
def test_opencv_12_and_14_coefficients_round_trip(random_cameras, tmp_path, n):
    cams = [c.__class__(c.name, c.K, np.r_[np.resize(c.dist, 8) * 0.5,
                                           np.full(n - 8, 0.01)], c.R, c.t, c.size)
            for c in random_cameras]
    rig = CameraRig(cams)
    write_opencv_yaml(rig, tmp_path)
    back = read_opencv_yaml(tmp_path / "intri.yml", tmp_path / "extri.yml")
    _same_projections(rig, back)
    X = _points(50)
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cams[0].R)[0], cams[0].t, cams[0].K,
                               cams[0].dist)
    np.testing.assert_allclose(back[0].project(X)[0], ref.reshape(-1, 2), atol=1e-6)


def test_anipose_fisheye_is_refused_not_misread(random_cameras, tmp_path):
    write_toml(CameraRig(random_cameras[:2]), tmp_path / "calibration.toml")
    text = (tmp_path / "calibration.toml").read_text().replace('name = "cam0"',
                                                               'name = "cam0"\nfisheye = true')
    (tmp_path / "calibration.toml").write_text(text)
    with pytest.raises(CalibrationError, match=r"camera 'cam0'.*fisheye = true"):
        read_calibration(tmp_path)


def test_pose2sim_project_folder_reads_calibration_not_config(random_cameras, tmp_path):
    """Pose2Sim keeps Config.toml at the project's root and Calib_*.toml in calibration/."""
    (tmp_path / "Config.toml").write_text('[project]\nframe_rate = 60\n[pose]\nmode = "x"\n')
    (tmp_path / "calibration").mkdir()
    write_toml(CameraRig(random_cameras), tmp_path / "calibration" / "Calib_board.toml")
    assert find_calibration(tmp_path).name == "Calib_board.toml"
    _same_projections(CameraRig(random_cameras), read_calibration(tmp_path))
