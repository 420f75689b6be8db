"""Frame selections: known indices, clear errors, decoding only what is selected."""

from __future__ import annotations

import numpy as np
import pytest

from nsd.core.errors import ConfigError
from nsd.io.footage import MultiViewFootage
from nsd.io.frame_selection import iter_selected, select_frames
from tests.conftest import write_video


def test_select_frames_known_values():
    assert select_frames("all", 4).tolist() == [0, 1, 2, 3]
    assert select_frames({"start": 1, "stop": None, "step": 2}, 6).tolist() == [1, 3, 5]
    assert select_frames({"stop": 100}, 3).tolist() == [0, 1, 2]  # stop is clipped
    assert select_frames([5, 0, 5, 2], 6).tolist() == [0, 2, 5]


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("some", "'all', a range or a list"),
        ({"start": 9}, r"frames.start=9 is outside"),
        ({"step": 0}, "frames.step must be >= 1"),
        ({"begin": 0}, "unknown keys"),
        ([0, 7], r"frames \[7\] are outside"),
        ([1.5], "must be an integer"),
        ({"start": 2, "stop": 2}, "selects no frame"),
    ],
)
def test_select_frames_bad_input(spec, match):
    with pytest.raises(ConfigError, match=match):
        select_frames(spec, 4)


@pytest.mark.parametrize("frames", [[0, 1, 2, 3], [1, 3], [2]])
def test_iter_selected_image_folders_match_random_access(tiny_scene, frames):
    footage = MultiViewFootage(tiny_scene)
    got = list(iter_selected(footage, np.asarray(frames)))
    assert [t for t, _ in got] == frames
    for t, views in got:
        assert len(views) == footage.num_views
        for v, src in enumerate(footage.sources):
            np.testing.assert_array_equal(views[v], src.read(t))


def test_iter_selected_video_skips_decoded_frames(tiny_scene):
    rng = np.random.default_rng(0)
    clips = {}
    for name in ("left", "right"):
        import shutil

        shutil.rmtree(tiny_scene / name)
        clips[name] = rng.integers(0, 256, (7, 24, 32, 3), dtype=np.uint8)
        write_video(tiny_scene / f"{name}.avi", clips[name])
    footage = MultiViewFootage(tiny_scene)
    got = list(iter_selected(footage, np.asarray([1, 4, 6])))
    assert [t for t, _ in got] == [1, 4, 6]
    for t, views in got:  # sequential decoding gives what random access gives
        for v, src in enumerate(footage.sources):
            np.testing.assert_array_equal(views[v], src.read(t))
