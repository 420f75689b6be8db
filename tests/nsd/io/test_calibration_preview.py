"""The calibration preview and table (nsd/io/calibration_preview.py) and nsd-calib's writers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_calibration, write_calibration
from nsd.core.errors import CalibrationError
from nsd.io.calibration_preview import PANEL, look_at_point, preview, rig_table
from tests.conftest import look_at_camera


def _rig() -> CameraRig:
    target = np.array([0.5, -0.2, 0.0])
    return CameraRig([look_at_camera(f"c{i}", np.array([4 * np.cos(a), 4 * np.sin(a), 2.0]),
                                     target) for i, a in enumerate((0.3, 1.9, 3.6))])


def test_look_at_point_is_where_the_axes_meet():
    np.testing.assert_allclose(look_at_point(_rig()), [0.5, -0.2, 0.0], atol=1e-9)


def test_rig_table_lists_every_camera_and_the_target():
    table = rig_table(_rig())
    assert all(f"| c{i} | 320x240 |" in table for i in range(3))
    assert "meet nearest [0.5, -0.2, 0.0]" in table


def test_the_floor_grid_and_axes_are_drawn_where_the_calibration_projects_them():
    """Each camera panel (grey canvas) is coloured exactly where the world origin projects
    (the axes start there) and keeps its grey where nothing projects (the sky)."""
    rig = _rig()
    img = preview(rig)
    scale = PANEL / 320
    for v, cam in enumerate(rig):
        r, c = divmod(2 + v, 4)
        panel = img[r * (PANEL + 4): r * (PANEL + 4) + 240 * PANEL // 320,
                    c * (PANEL + 4): c * (PANEL + 4) + PANEL]
        uv, _ = cam.project(np.zeros((1, 3)))
        u, w = (round(float(x) * scale) for x in uv[0])
        assert not (panel[w, u] == 128).all(), f"camera {cam.name}: origin not drawn"
        assert (panel[3:10, PANEL - 40: PANEL - 5] == 128).all()  # top right: the sky


@pytest.mark.parametrize(("name", "fmt"), [("x.toml", "anipose"), ("camera_array.toml",
                                                                     "caliscope"),
                                            ("calibration_a.json", "panoptic")])
def test_write_calibration_picks_the_format_by_name(tmp_path, name, fmt):
    assert write_calibration(_rig(), tmp_path / name) == fmt
    back = read_calibration(tmp_path / name)
    names = ["cam_0", "cam_1", "cam_2"] if fmt == "caliscope" else ["c0", "c1", "c2"]
    assert back.names == names


def test_write_calibration_needs_a_format_for_a_folder(tmp_path):
    with pytest.raises(CalibrationError, match="give the format"):
        write_calibration(_rig(), tmp_path / "model")
    write_calibration(_rig(), tmp_path / "model", "colmap")
    assert read_calibration(tmp_path / "model").names == ["c0", "c1", "c2"]


def test_nsd_calib_converts_and_draws(tmp_path):
    write_calibration(_rig(), tmp_path / "calibration.toml")
    res = subprocess.run(
        [str(Path(sys.executable).parent / "nsd-calib"), f"calibration={tmp_path}",
         f"convert={tmp_path / 'out' / 'camera_array.toml'}", f"preview={tmp_path / 'rig.png'}"],
        capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "| c1 | 320x240 |" in res.stdout and (tmp_path / "rig.png").stat().st_size > 1000
    assert read_calibration(tmp_path / "out" / "camera_array.toml").names == ["cam_0", "cam_1",
                                                                              "cam_2"]
