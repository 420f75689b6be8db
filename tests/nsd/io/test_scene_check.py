"""The scene check before any long work (nsd/io/scene_check.py), on the tiny scene."""

from __future__ import annotations

import os
import re
import shutil

import cv2
import numpy as np
import pytest

from nsd.core.errors import CalibrationError, FootageError, SceneError
from nsd.io.scene_check import check_scene, scene_fingerprint


def _frames(scene, cam):
    return sorted((scene / cam).glob("*.png"))


def test_a_good_scene_passes_with_its_figures(tiny_scene):
    c = check_scene(tiny_scene)
    assert c.cameras == ["left", "right"] and c.frames == 4
    assert c.sizes == {"left": (32, 24), "right": (32, 24)}
    # both cameras stand 4 m from the origin, 90 degrees apart: 4 * sqrt(2) m
    assert c.camera_spacing == pytest.approx(4 * np.sqrt(2), rel=1e-6)


def test_frame_names_that_disagree_across_cameras_are_an_error(tiny_scene):
    """'right' dropped frame 1 and numbered on: as many files, shifted names."""
    for f in reversed(_frames(tiny_scene, "right")[1:]):
        f.rename(f.with_name(f"{int(f.stem) + 1:06d}.png"))
    with pytest.raises(SceneError, match=r"camera 'right': frame 1 is 000002.png where camera "
                                         r"'left' has 000001.png"):
        check_scene(tiny_scene)


def test_an_image_of_another_size_is_named(tiny_scene):
    f = _frames(tiny_scene, "left")[2]
    cv2.imwrite(str(f), np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(SceneError, match=r"camera 'left' \(.*000002.png, frame 2\): image is "
                                         r"12x10 but the camera's first frame is 32x24"):
        check_scene(tiny_scene)


def test_a_file_that_is_not_an_image_is_named(tiny_scene):
    _frames(tiny_scene, "right")[3].write_bytes(b"not an image")
    with pytest.raises(FootageError, match=r"camera 'right' \(.*000003.png, frame 3\)"):
        check_scene(tiny_scene)


def test_a_calibration_in_millimetres_is_converted_and_said(tiny_scene, caplog):
    p = tiny_scene / "calibration.toml"
    p.write_text(p.read_text().replace("translation = [0.0, 0.0, 4.0]",
                                       "translation = [0.0, 0.0, 4000.0]"))
    with caplog.at_level("WARNING"):
        check = check_scene(tiny_scene)
    assert any(re.search(r"5657 units apart, read as millimetres", w) for w in check.warnings)
    said = [r for r in caplog.records if "read as millimetres" in r.getMessage()]
    assert len(said) == 1, [r.getMessage() for r in said]  # once, not again by the check
    assert check.camera_spacing == pytest.approx(5.657, abs=1e-3)
    with pytest.raises(CalibrationError, match=r"5657 m apart.*units=mm"):
        check_scene(tiny_scene, units="m")  # the user says metres: refused, with what to do


def test_one_camera_is_refused_before_training(tiny_scene):
    with pytest.raises(SceneError, match="needs at least 2"):
        check_scene(tiny_scene, cameras=["left"])


@pytest.mark.parametrize("workers", [1, 2])
def test_blank_and_saturated_frames_are_warned_by_camera_and_frame(tiny_scene, workers):
    """The same warnings, in the cameras' order, whether one process reads every camera or
    a process reads each."""
    f0, f2 = _frames(tiny_scene, "left")[0], _frames(tiny_scene, "right")[2]
    cv2.imwrite(str(f0), np.zeros((24, 32, 3), np.uint8))
    cv2.imwrite(str(f2), np.full((24, 32, 3), 255, np.uint8))
    w = [x for x in check_scene(tiny_scene, workers=workers).warnings if "frames" in x]
    assert re.match(r"camera 'left': frames 0 are blank \(dark\)", w[0]), w
    assert re.match(r"camera 'right': frames 2 are saturated \(white\)", w[1]), w


def test_footage_in_which_nothing_moves_is_warned(tiny_scene):
    for cam in ("left", "right"):
        fs = _frames(tiny_scene, cam)
        for f in fs[1:]:
            shutil.copy(fs[0], f)
    assert any(x.startswith("nothing moves in any camera") for x in check_scene(
        tiny_scene).warnings)


def test_the_tiny_scene_moves(tiny_scene):
    assert not any("nothing moves" in x for x in check_scene(tiny_scene).warnings)


def test_footage_the_calibration_does_not_name_is_warned(tiny_scene):
    shutil.copytree(tiny_scene / "left", tiny_scene / "extra_cam")
    w = check_scene(tiny_scene).warnings
    assert any("extra_cam is not a camera of the calibration" in x for x in w)


def test_fingerprint_follows_the_footage_not_the_caches(tiny_scene):
    before = scene_fingerprint(tiny_scene)
    (tiny_scene / ".cache").mkdir()
    (tiny_scene / ".cache" / "bg.npz").write_bytes(b"x")
    assert scene_fingerprint(tiny_scene) == before
    f = _frames(tiny_scene, "left")[1]
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert scene_fingerprint(tiny_scene) != before


def test_frames_identical_to_the_background_are_listed(tiny_scene):
    """Frames 0-2 equal (the median is them), frame 3 differs: 0-2 show only background."""
    for cam in ("left", "right"):
        fs = _frames(tiny_scene, cam)
        for f in fs[1:3]:
            shutil.copy(fs[0], f)
    w = check_scene(tiny_scene).warnings
    assert any(x.startswith("camera 'left': frames 0-2 (of 4 sampled) are identical to the "
                            "median background") for x in w), w
    assert not any("nothing moves" in x for x in w)


def test_background_plates_are_listed_and_checked(tiny_scene):
    (tiny_scene / "background").mkdir()
    cv2.imwrite(str(tiny_scene / "background" / "right.png"), np.zeros((24, 32, 3), np.uint8))
    assert list(check_scene(tiny_scene).plates) == ["right"]
    cv2.imwrite(str(tiny_scene / "background" / "right.png"), np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(FootageError, match=r"camera 'right': background plate .* is 5x5"):
        check_scene(tiny_scene)


def test_footage_too_short_for_a_median_background_is_warned_unless_plates_replace_it(tiny_scene):
    """4 frames: subjects that stay are part of the median (the real two-mouse recording of
    3 frames ran silently); plates for every camera replace the median and end the warning."""
    short = [w for w in check_scene(tiny_scene).warnings if "the footage has 4 frames" in w]
    assert len(short) == 1 and "background plate" in short[0]
    (tiny_scene / "background").mkdir()
    cv2.imwrite(str(tiny_scene / "background" / "right.png"), np.zeros((24, 32, 3), np.uint8))
    assert any("4 frames" in w for w in check_scene(tiny_scene).warnings)  # one camera left
    cv2.imwrite(str(tiny_scene / "background" / "left.png"), np.zeros((24, 32, 3), np.uint8))
    assert not any("4 frames" in w for w in check_scene(tiny_scene).warnings)


def test_what_the_footage_reader_found_is_among_the_warnings(tiny_scene):
    """A camera one frame short is trimmed: said by the footage reader, listed by the check
    (nsd-check prints only the check's warnings)."""
    _frames(tiny_scene, "right")[3].unlink()
    w = check_scene(tiny_scene).warnings
    assert any(re.search(r"different numbers of frames \('left' .*: 4, 'right' .*: 3\)", x)
               for x in w)
