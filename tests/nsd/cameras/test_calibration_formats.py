"""The other calibration formats: round trips by projection, known values, the dispatch."""

from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest
import torch

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
    write_calibration,
    write_opencv_yaml,
    write_toml,
)
from nsd.cameras.dlt import read_dlt, write_dlt
from nsd.cameras.projection import project_points
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


def _fisheye_rig(random_cameras) -> CameraRig:
    """Cameras 0 and 2 with Kannala-Brandt lenses, the others as they are (a mixed rig)."""
    k = np.array([-0.05, 0.01, -0.002, 0.0004])
    return CameraRig([dataclasses.replace(c, dist=k * (1 + i), fisheye=True) if i in (0, 2)
                      else c for i, c in enumerate(random_cameras)])


@pytest.mark.parametrize("fmt", ["anipose", "colmap", "colmap_bin"])
def test_fisheye_round_trips_and_projects_like_cv2_fisheye(random_cameras, tmp_path, fmt):
    rig = _fisheye_rig(random_cameras)
    path = tmp_path / ("calibration.toml" if fmt == "anipose" else "model")
    write_calibration(rig, path, fmt)
    back = read_calibration(path if fmt == "anipose" else path / (
        "cameras.txt" if fmt == "colmap" else "cameras.bin"))
    assert [c.fisheye for c in back] == [c.fisheye for c in rig]
    _same_projections(rig, back)
    X = _points(200)
    for c in (back[0], back[2]):
        ref, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(c.R)[0], c.t, c.K,
                                           c.dist)
        np.testing.assert_allclose(c.project(X)[0], ref.reshape(-1, 2), atol=1e-6)


def test_fisheye_unprojects_like_cv2_fisheye_and_batches_with_pinholes(random_cameras):
    rig = _fisheye_rig(random_cameras)
    c = rig[2]
    uv = np.random.default_rng(0).uniform([0, 0], c.size, (300, 2))
    ref = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), c.K, c.dist).reshape(-1, 2)
    rays = c.unproject(uv) @ c.R.T  # camera-frame unit rays
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ref, atol=1e-7)
    cams = rig.stacked(torch.float64)  # one batch: lens vectors for every camera
    X = torch.as_tensor(_points(100))
    uv_b, _ = project_points(X.expand(len(rig), -1, -1), cams.K, cams.R, cams.t, cams.dist)
    for v, cam in enumerate(rig):
        np.testing.assert_allclose(uv_b[v].numpy(), cam.project(X.numpy())[0], atol=1e-9)


@pytest.mark.parametrize("fmt", ["opencv", "panoptic", "caliscope"])
def test_formats_without_fisheye_refuse_to_write_one(random_cameras, tmp_path, fmt):
    name = {"opencv": "yml", "panoptic": "c.json", "caliscope": "camera_array.toml"}[fmt]
    with pytest.raises(CalibrationError, match=r"camera 'cam0' has a fisheye lens.*" + "TOML"):
        write_calibration(_fisheye_rig(random_cameras), tmp_path / name, fmt)


def test_a_fisheye_camera_needs_four_coefficients(random_cameras):
    with pytest.raises(CalibrationError, match=r"fisheye.*4 coefficients.*got 5"):
        dataclasses.replace(random_cameras[2], fisheye=True)


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


def test_pose2sim_project_folder_reads_calibration_not_config(random_cameras, tmp_path):
    """Pose2Sim keeps Config.toml at the project's root and Calib_*.toml in calibration/."""
    (tmp_path / "Config.toml").write_text('[project]\nframe_rate = 60\n[pose]\nmode = "x"\n')
    (tmp_path / "calibration").mkdir()
    write_toml(CameraRig(random_cameras), tmp_path / "calibration" / "Calib_board.toml")
    assert find_calibration(tmp_path).name == "Calib_board.toml"
    _same_projections(CameraRig(random_cameras), read_calibration(tmp_path))


def _pinhole_rig(random_cameras) -> CameraRig:
    """The random cameras without lens distortion, one with skew (a DLT holds 11 values)."""
    cams = [dataclasses.replace(c, dist=np.zeros(0)) for c in random_cameras]
    K = cams[2].K.copy()
    K[0, 1] = 3.0
    cams[2] = dataclasses.replace(cams[2], K=K)
    return CameraRig([dataclasses.replace(c, name=f"cam{i + 1}") for i, c in enumerate(cams)])


@pytest.mark.parametrize("origin", ["lower_left", "upper_left"])
def test_dlt_round_trip_and_known_projection(random_cameras, tmp_path, origin):
    rig = _pinhole_rig(random_cameras)
    write_dlt(rig, tmp_path / "x_dlt-coefs.csv", origin)
    back = read_dlt(tmp_path / "x_dlt-coefs.csv", {c.name: c.size for c in rig}, origin)
    _same_projections(rig, back)
    for a, b in zip(rig, back, strict=True):
        np.testing.assert_allclose(b.K, a.K, atol=1e-6)
        np.testing.assert_allclose(b.R, a.R, atol=1e-9)
    # the DLT equations themselves, in the tools' image coordinates
    L = np.loadtxt(tmp_path / "x_dlt-coefs.csv", delimiter=",")[:, 0]
    X = _points(20)
    den = X @ L[8:11] + 1
    u, v = (X @ L[0:3] + L[3]) / den, (X @ L[4:7] + L[7]) / den
    uv, _ = rig[0].project(X)
    H = rig[0].size[1]
    expect = (uv[:, 0] + 1, H - uv[:, 1]) if origin == "lower_left" else (uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(u, expect[0], atol=1e-6)
    np.testing.assert_allclose(v, expect[1], atol=1e-6)


def test_dlt_in_a_scene_folder_takes_sizes_from_the_footage(random_cameras, tmp_path):
    rig = _pinhole_rig(random_cameras)[:2]
    for c in rig:
        (tmp_path / c.name).mkdir()
        cv2.imwrite(str(tmp_path / c.name / "000000.png"),
                    np.zeros((c.size[1], c.size[0], 3), np.uint8))
    write_calibration(rig, tmp_path / "trial_dlt-coefs.csv")
    assert find_calibration(tmp_path).name == "trial_dlt-coefs.csv"
    _same_projections(rig, read_calibration(tmp_path))
    shutil.rmtree(tmp_path / "cam2")
    with pytest.raises(CalibrationError, match=r"camera 'cam2'.*no image size"):
        read_calibration(tmp_path)


def test_dlt_refuses_what_it_cannot_hold(random_cameras, tmp_path):
    with pytest.raises(CalibrationError, match=r"camera 'cam1'.*lens distortion"):
        write_dlt(CameraRig(random_cameras[1:2]).select(["cam1"]), tmp_path / "d.csv")
    (tmp_path / "bad_dlt.csv").write_text("1,2\n3,4\n")
    with pytest.raises(CalibrationError, match="11 rows"):
        read_dlt(tmp_path / "bad_dlt.csv", {})
    rig = _pinhole_rig(random_cameras)[:1]
    write_dlt(rig, tmp_path / "m_dlt.csv")
    L = np.loadtxt(tmp_path / "m_dlt.csv", delimiter=",").reshape(11, 1)
    L[[0, 4, 8]] *= -1  # X mirrored: a left-handed world
    np.savetxt(tmp_path / "m_dlt.csv", L, delimiter=",")
    with pytest.raises(CalibrationError, match="left-handed"):
        read_dlt(tmp_path / "m_dlt.csv", {"cam1": rig[0].size})


@pytest.mark.parametrize("fisheye", [False, True])
def test_anipose_toml_is_read_by_aniposelib_and_back(random_cameras, tmp_path, fisheye):
    """Our TOML loaded by aniposelib (anipose's own library) projects like our rig, and
    a TOML aniposelib writes reads back to the same projections, fisheye lenses included."""
    aniposelib = pytest.importorskip("aniposelib.cameras")  # tools/setup.sh --dev installs it
    rig = _fisheye_rig(random_cameras) if fisheye else CameraRig(random_cameras)
    write_toml(rig, tmp_path / "ours.toml")
    group = aniposelib.CameraGroup.load(str(tmp_path / "ours.toml"))
    X = _points(100)
    theirs = group.project(X)
    for v, cam in enumerate(rig):
        np.testing.assert_allclose(theirs[v], cam.project(X)[0], atol=1e-6)
    group.dump(str(tmp_path / "theirs.toml"))
    _same_projections(rig, read_calibration(tmp_path / "theirs.toml"))
