"""Calibration files: round trips, the three readers, and bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import (
    find_calibration,
    read_calibration,
    read_opencv_yaml,
    read_qca,
    read_toml,
    write_opencv_yaml,
    write_toml,
)
from nsd.core.errors import CalibrationError
from tests.conftest import FIXTURES


class TestToml:
    def test_round_trip(self, random_cameras, tmp_path):
        rig = CameraRig(random_cameras)
        write_toml(rig, tmp_path / "calibration.toml")
        back = read_toml(tmp_path / "calibration.toml")
        assert back.names == rig.names
        for a, b in zip(rig, back, strict=True):
            assert a.size == b.size
            np.testing.assert_array_equal(a.K, b.K)
            np.testing.assert_array_equal(a.dist, b.dist)
            np.testing.assert_array_equal(a.t, b.t)
            # R goes through a Rodrigues vector: equal to float rounding
            np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-14)
        # a second generation is bit-identical to the first
        write_toml(back, tmp_path / "again.toml")
        again = read_toml(tmp_path / "again.toml")
        assert again.equals(back, atol=1e-15)

    def test_hand_written_fixture(self):
        rig = read_toml(FIXTURES / "tiny_scene" / "calibration.toml")
        assert rig.names == ["left", "right"]
        assert rig["left"].size == (32, 24)
        np.testing.assert_allclose(rig["left"].center, [4, 0, 0], atol=1e-12)
        np.testing.assert_allclose(rig["right"].viewing_direction, [0, 1, 0], atol=1e-12)

    def test_missing_file(self, tmp_path):
        with pytest.raises(CalibrationError, match="does not exist"):
            read_toml(tmp_path / "none.toml")

    def test_not_toml(self, tmp_path):
        (tmp_path / "c.toml").write_text("[cam_0\nname=")
        with pytest.raises(CalibrationError, match="not valid TOML"):
            read_toml(tmp_path / "c.toml")

    def test_missing_key_names_camera(self, tmp_path):
        (tmp_path / "c.toml").write_text(
            '[cam_0]\nname = "A"\nmatrix = [[1,0,0],[0,1,0],[0,0,1]]\n'
        )
        with pytest.raises(CalibrationError, match=r"camera 'A' \(\[cam_0\]\).*missing"):
            read_toml(tmp_path / "c.toml")

    def test_singular_matrix_names_file(self, tmp_path):
        text = (FIXTURES / "tiny_scene" / "calibration.toml").read_text()
        (tmp_path / "c.toml").write_text(text.replace("[40.0, 0.0, 15.5]", "[0.0, 0.0, 15.5]"))
        with pytest.raises(CalibrationError, match=r"camera 'left' in .*c.toml: K is singular"):
            read_toml(tmp_path / "c.toml")


class TestOpenCVYaml:
    def test_round_trip(self, random_cameras, tmp_path):
        rig = CameraRig(random_cameras)
        write_opencv_yaml(rig, tmp_path)
        back = read_opencv_yaml(tmp_path / "intri.yml")
        assert back.equals(rig, atol=0.0)  # Rot_<name> holds the exact matrix

    def test_rodrigues_only_and_no_size(self, random_cameras, tmp_path):
        """EasyMocap files may store only R_<name> (Rodrigues) and no image size."""
        import cv2

        cam = random_cameras[1]
        fs = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        fs.write("", "01")
        fs.endWriteStruct()
        fs.write("K_01", cam.K)
        fs.write("dist_01", cam.dist.reshape(1, -1))
        fs.release()
        fs = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        fs.write("", "01")
        fs.endWriteStruct()
        fs.write("R_01", cv2.Rodrigues(cam.R)[0])
        fs.write("T_01", cam.t.reshape(3, 1))
        fs.release()
        back = read_calibration(tmp_path / "intri.yml")
        assert back.names == ["01"] and back[0].size is None
        np.testing.assert_allclose(back[0].R, cam.R, atol=1e-12)

    def test_missing_key(self, random_cameras, tmp_path):
        write_opencv_yaml(CameraRig(random_cameras[:1]), tmp_path)
        text = (tmp_path / "extri.yml").read_text()
        (tmp_path / "extri.yml").write_text(text.replace("T_cam0", "X_cam0"))
        with pytest.raises(CalibrationError, match=r"extri.yml: missing 'T_cam0'"):
            read_opencv_yaml(tmp_path)


def _qca_xml(rig: CameraRig, left: int = 0, top: int = 0) -> str:
    """Write cameras the way a Qualisys export stores them (see nsd.cameras.calibration_io)."""
    rows = []
    for c in rig:
        w, h = c.size
        stored = np.diag([1.0, -1.0, -1.0]) @ c.R  # = (camera-to-world)^T, row by row
        r = " ".join(
            f'r{i + 1}{j + 1}="{float(stored[i, j])!r}"' for i in range(3) for j in range(3)
        )
        pos = (c.center * 1000.0).tolist()
        d = (c.dist[:4] * 64).tolist()
        rows.append(f"""
    <camera active="1" serial="{c.name}" viewrotation="0">
      <fov_video bottom="{top + h - 1}" left="{left}" right="{left + w - 1}" top="{top}"/>
      <transform {r} x="{pos[0]!s}" y="{pos[1]!s}" z="{pos[2]!s}"/>
      <intrinsic centerPointU="{(c.K[0, 2] + left) * 64!s}"
        centerPointV="{(c.K[1, 2] + top) * 64!s}"
        focalLengthU="{c.K[0, 0] * 64!s}" focalLengthV="{c.K[1, 1] * 64!s}"
        radialDistortion1="{d[0]!s}" radialDistortion2="{d[1]!s}" radialDistortion3="0.0"
        tangentalDistortion1="{d[2]!s}" tangentalDistortion2="{d[3]!s}" skew="0"/>
    </camera>""")
    return f"<?xml version='1.0'?>\n<calibration><cameras>{''.join(rows)}\n</cameras></calibration>"


class TestQca:
    def test_conversion(self, random_cameras, tmp_path):
        cams = [c for c in random_cameras if c.dist.size in (4, 5) and not c.dist[4:].any()]
        rig = CameraRig(cams)
        (tmp_path / "Calib.qca.txt").write_text(_qca_xml(rig, left=8, top=4))
        back = read_calibration(tmp_path / "Calib.qca.txt")
        assert back.names == rig.names
        X = np.random.default_rng(0).uniform(-1, 1, (20, 3))
        for a, b in zip(rig, back, strict=True):
            assert b.size == a.size
            np.testing.assert_allclose(b.K, a.K, atol=1e-9)
            np.testing.assert_allclose(b.R, a.R, atol=1e-12)
            np.testing.assert_allclose(b.center, a.center, atol=1e-12)
            np.testing.assert_allclose(b.project(X)[0], a.project(X)[0], atol=1e-6)

    def test_bad_value_names_camera(self, random_cameras, tmp_path):
        xml = _qca_xml(CameraRig(random_cameras[1:2])).replace('focalLengthU="', 'focalLengthU="x')
        (tmp_path / "c.qca.txt").write_text(xml)
        with pytest.raises(CalibrationError, match=r"camera 'cam1' in .*c.qca.txt"):
            read_qca(tmp_path / "c.qca.txt")

    def test_not_xml(self, tmp_path):
        (tmp_path / "c.qca.txt").write_text("<calibration><cameras>")
        with pytest.raises(CalibrationError, match="not a Qualisys XML"):
            read_qca(tmp_path / "c.qca.txt")


def test_find_calibration(tmp_path: Path, random_cameras):
    with pytest.raises(CalibrationError, match="no calibration file"):
        find_calibration(tmp_path)
    write_toml(CameraRig(random_cameras), tmp_path / "calibration" / "calibration.toml")
    assert find_calibration(tmp_path).name == "calibration.toml"
    assert read_calibration(tmp_path).names == [c.name for c in random_cameras]
