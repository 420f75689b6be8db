"""Front and back from the subject's own track (netepu.pipeline.heading)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from netepu.geometry.inverse import rotate_about_up
from netepu.pipeline.heading import AMBIGUOUS, expected_headings, heading, turned_pose, turns
from nsd.synth.skeleton import get_species

UP = (0.0, 0.0, 1.0)


def _posed(rest: np.ndarray, angle: float, up=UP, at=(2.0, -1.0, 0.0)) -> np.ndarray:
    """The rest pose turned by ``angle`` about ``up`` and moved to ``at``."""
    r = torch.as_tensor(rest - rest.mean(0), dtype=torch.float64)
    return rotate_about_up(r, angle, torch.tensor(up, dtype=torch.float64)).numpy() + at


@pytest.mark.parametrize("species", ["biped", "quadruped"])
@pytest.mark.parametrize("degrees", [0.0, 35.0, 90.0, -120.0, 179.0])
def test_the_heading_of_the_rest_pose_turned_is_the_turn(species, degrees):
    """Both species' rest poses turned by a known angle about z (and moved) have that heading."""
    rest = get_species(species).rest
    got = heading(_posed(rest, math.radians(degrees)), rest, UP)
    assert math.degrees(got) == pytest.approx(degrees, abs=1e-6)


def test_the_heading_about_another_up_axis_turns_with_the_body():
    """With y up, turning the body by an angle about y changes its heading by that angle
    (whatever axis the ground plane's e1 is)."""
    rest = get_species("quadruped").rest
    up = (0.0, 1.0, 0.0)
    r = torch.as_tensor(rest - rest.mean(0), dtype=torch.float64)
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    stood = (r @ tilt.T).numpy()  # the body's z (up) now along y
    base = heading(stood, rest, up)
    for degrees in (30.0, -100.0):
        turned = rotate_about_up(torch.as_tensor(stood), math.radians(degrees),
                                 torch.tensor(up, dtype=torch.float64)).numpy()
        change = (heading(turned, rest, up) - base + math.pi) % (2 * math.pi) - math.pi
        assert math.degrees(change) == pytest.approx(degrees, abs=1e-6)


def test_a_turned_pose_keeps_its_centroid_and_shape_and_turns_its_heading():
    rest = get_species("quadruped").rest
    pose = _posed(rest, 0.3)
    out = turned_pose(pose, 2.0, UP)
    np.testing.assert_allclose(out.mean(0), pose.mean(0), atol=1e-12)
    d = np.linalg.norm(pose[:, None] - pose[None], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(out[:, None] - out[None], axis=-1), d, atol=1e-12)
    assert heading(out, rest, UP) == pytest.approx(2.3, abs=1e-9)


def test_the_neighbours_expect_the_short_arc_midpoint_per_subject():
    """Known cases: the midpoint of the frames before and after (across +-180 degrees too);
    a track's ends take their one neighbour; a lone fit, or neighbours facing nearly opposite
    ways, expect nothing; the frames' order, not the list's, makes the neighbours."""
    r = math.radians
    frames = [20, 0, 10, 30, 0, 10, 20, 5, 0, 10, 20]
    subjects = [1, 1, 1, 1, 2, 2, 2, 3, 4, 4, 4]
    headings = [r(40), r(0), r(100), r(60), r(170), r(0), r(-170), r(50), r(0), r(10),
                r(0) + AMBIGUOUS + r(5)]
    got = expected_headings(frames, subjects, headings)
    want = [r(80), r(100), r(20), r(40), r(0), r(180), r(0), None, r(10), None, r(10)]
    for g, w in zip(got, want, strict=True):
        if w is None:
            assert g is None
        else:
            assert math.cos(g - w) == pytest.approx(1.0, abs=1e-12)


def test_only_fits_more_than_a_quarter_turn_off_are_turned_and_by_what_is_missing():
    """A track facing 0 degrees with one fit at 186 (its neighbours then face 174 degrees
    apart: they expect nothing), 100 or 80 degrees."""
    r = math.radians
    frames, subjects = [0, 10, 20, 30, 40], [7] * 5
    got = turns(frames, subjects, [r(0), r(0), r(186), r(0), r(0)])
    assert set(got) == {2} and math.degrees(got[2]) == pytest.approx(174.0, abs=1e-9)
    got = turns(frames, subjects, [r(0), r(0), r(100), r(0), r(0)])
    assert set(got) == {2} and math.degrees(got[2]) == pytest.approx(-100.0, abs=1e-9)
    assert turns(frames, subjects, [r(0), r(0), r(80), r(0), r(0)]) == {}


def test_neighbours_further_apart_than_the_gap_expect_nothing():
    """Frames 0, 10 and 40 of one track: with a gap of 15 frames frame 10 hears only frame 0,
    frame 40 nobody; with no gap every neighbour counts."""
    r = math.radians
    frames, subjects, headings = [0, 10, 40], [1, 1, 1], [r(0), r(20), r(100)]
    got = expected_headings(frames, subjects, headings, max_gap=15)
    assert got[0] == pytest.approx(r(20)) and got[1] == pytest.approx(r(0)) and got[2] is None
    assert all(g is not None for g in expected_headings(frames, subjects, headings))
    assert turns(frames, subjects, [r(0), r(170), r(0)], max_gap=15) == {
        0: pytest.approx(r(170)), 1: pytest.approx(r(-170))}
    assert turns(frames, subjects, [r(0), r(170), r(0)], max_gap=5) == {}
