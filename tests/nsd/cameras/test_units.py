"""The calibration's length unit (nsd/cameras/units.py): every rig is used in metres."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from nsd.cameras.calibration_io import read_calibration, read_toml, write_toml
from nsd.cameras.units import AUTO_MM_SPACING, UNITS, camera_spacing, in_metres
from nsd.core.errors import CalibrationError
from nsd.core.validation import RULES
from nsd.io.scene_data import SceneData
from nsd.synth.scene import tiny_config, write_scene


def _in_unit(scene, out, per_metre: float):
    """A copy of ``scene`` whose calibration file says the same rig in another unit."""
    shutil.copytree(scene, out)
    rig = read_toml(scene / "calibration.toml")
    write_toml(rig.with_translation_scale(per_metre), out / "calibration.toml")
    return out


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("units")
    metres = write_scene(tiny_config(), root / "m")
    return {"m": metres, "mm": _in_unit(metres, root / "mm", 1000.0),
            "cm": _in_unit(metres, root / "cm", 100.0)}


def test_auto_reads_millimetres_and_says_so(scenes):
    ref = read_calibration(scenes["m"])
    rig = read_calibration(scenes["mm"])
    assert rig.equals(ref, atol=1e-9)
    assert "millimetres" in rig.units_note and ref.units_note == ""
    assert camera_spacing(read_calibration(scenes["mm"], "m")) > AUTO_MM_SPACING


def test_the_inferred_unit_is_warned_once_per_file_and_noted_every_time(tmp_path, scenes,
                                                                        caplog):
    """Every stage reads the calibration again: one warning per file, the note on every rig."""
    other = _in_unit(scenes["m"], tmp_path / "mm2", 1000.0)
    with caplog.at_level("WARNING", logger="nsd.cameras.units"):
        rigs = [read_calibration(path) for path in (other, other, other / "calibration.toml")]
        first = len(caplog.records)
        rigs.append(read_calibration(scenes["mm"]))  # another file warns (or did already)
    assert first == 1 and "mm2" in caplog.records[0].getMessage()
    assert all("millimetres" in rig.units_note for rig in rigs)


@pytest.mark.parametrize("unit", ["mm", "cm"])
def test_a_stated_unit_converts(scenes, unit):
    assert read_calibration(scenes[unit], unit).equals(read_calibration(scenes["m"]), atol=1e-9)


def test_centimetres_are_not_guessed(scenes):
    """A 4-camera rig ~3 m wide reads ~300 units in cm: auto takes it for mm (documented);
    only units=cm gets it right."""
    ref = camera_spacing(read_calibration(scenes["m"]))
    assert camera_spacing(read_calibration(scenes["cm"])) == pytest.approx(ref / 10)


def test_an_unknown_unit_is_refused(scenes):
    with pytest.raises(CalibrationError, match="units='inch'"):
        read_calibration(scenes["m"], "inch")


def test_the_config_rule_knows_every_unit():
    assert set(RULES["data"]["units"].choices) == {"auto", *UNITS}


def test_a_millimetre_calibration_gives_the_same_decomposition(scenes):
    """The visual-hull decomposition (boxes, depths, pixel owners) of the same footage with
    the rig in metres and in millimetres, and what a wrong unit does."""
    def hull(scene, units):
        data = SceneData(scene, (64, 64), val_fraction=0.0, units=units)
        data.compute_multiview_proposals(2, 0.04, 0.04, resolution=24)
        return data
    a, b = hull(scenes["m"], "auto"), hull(scenes["mm"], "auto")
    torch.testing.assert_close(a.proposals, b.proposals, atol=1e-4, rtol=0)
    torch.testing.assert_close(a.proposal_depths, b.proposal_depths, atol=1e-5, rtol=0)
    assert torch.equal(a.owners, b.owners) and bool(a.proposal_valid.any())
    wrong = hull(scenes["mm"], "m")  # millimetres taken as metres: the hull's volume is off
    assert not torch.equal(wrong.owners, a.owners)


def test_in_metres_keeps_a_metre_rig(scenes):
    rig = read_calibration(scenes["m"], "m")
    assert in_metres(rig, "auto").equals(rig) and np.isfinite(camera_spacing(rig))
