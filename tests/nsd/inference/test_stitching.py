"""Identities from where the subjects go (nsd/inference/stitching.py)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from nsd.inference.stitching import cut_tracklets, motion_identities, stitch_tracklets


def test_a_track_is_cut_where_a_step_exceeds_jump_times_the_root_of_the_gap():
    x = np.array([1.0, 0.0, 0.0])
    p = {(0, 7): 0 * x, (1, 7): 0.9 * x,  # 0.9 <= 1: kept
         (5, 7): 2.8 * x,  # 1.9 over 4 frames <= 1 * sqrt(4): kept
         (6, 7): 3.9 * x,  # 1.1 > 1: cut
         (0, 8): 5 * x}  # another track: its own tracklet
    assert cut_tracklets(p, 1.0) == [[(0, 7), (1, 7), (5, 7)], [(6, 7)], [(0, 8)]]
    with pytest.raises(ValueError, match="jump"):
        cut_tracklets(p, 0.0)
    with pytest.raises(ValueError, match="k must be"):
        stitch_tracklets(p, cut_tracklets(p, 1.0), 0)


def _huddle(frames: int, rng: np.random.Generator):
    """Three bodies circling their own centres 0.75 apart (0.02 per frame), observed with
    noise 0.02 as tracks that swap bodies the way the export's tracker does: at frames 40 and
    90 one mixed frame (every subject between two bodies) moves each track onto the next
    body for good; at frame 60 one body is split and its piece seen alone for 2 frames."""
    centres = 0.75 / np.sqrt(3) * np.array([[np.cos(a), np.sin(a), 0.0]
                                             for a in 2 * np.pi * np.arange(3) / 3])
    t = np.arange(frames)
    body = np.stack([c + 0.12 * np.stack([np.cos(0.15 * t + i), np.sin(0.15 * t + i),
                                          0 * t], 1) for i, c in enumerate(centres)])
    positions, truth = {}, {}
    shift = 0
    for f in range(frames):
        mixed = f in (40, 90)
        if mixed:
            shift += 1
        for i in range(3):
            track = 1 + (i + shift) % 3  # the track that holds body i from here on
            p = (body[i, f] + body[(i + 1) % 3, f]) / 2 if mixed else body[i, f]
            positions[(f, track)] = p + 0.02 * rng.normal(size=3)
            truth[(f, track)] = -1 if mixed else i
        if f in (60, 61):
            positions[(f, 9)] = body[0, f] + np.array([0.05, 0, 0])
            truth[(f, 9)] = 0
    return positions, truth


def test_tracks_that_swap_bodies_in_a_mixed_frame_are_stitched_back_by_position():
    positions, truth = _huddle(150, np.random.default_rng(0))
    label, pieces = motion_identities(positions, 3, jump=0.2, handover=5)
    assert pieces == 3 + 2 * 3 * 2 + 1  # each track cut before and after each mixed frame
    known = [key for key, i in truth.items() if i >= 0]
    best = max(np.mean([perm[truth[key]] == label[key] for key in known])
               for perm in itertools.permutations(range(3)))
    assert best == 1.0
    raw = max(np.mean([perm[truth[key]] == key[1] - 1 for key in known])  # the tracks alone
              for perm in itertools.permutations(range(3)))
    assert raw < 0.5
    assert set(label.values()) == {0, 1, 2}
    for f in (40, 90):  # the mixed frames' subjects take three distinct trajectories
        assert len({label[(f, s)] for s in (1, 2, 3)}) == 3


def test_without_cutting_a_swap_is_kept():
    """A jump longer than any step never cuts: each track is one trajectory, swaps and all."""
    positions, _ = _huddle(150, np.random.default_rng(1))
    label, pieces = motion_identities(positions, 3, jump=100.0)
    assert pieces == 4
    assert all(label[(f, s)] == label[(0, s)] for f, s in positions if s != 9)


def test_never_more_trajectories_than_individuals():
    """A fourth long tracklet beside three bodies (a ghost) shares the nearest trajectory."""
    x = np.array([1.0, 0.0, 0.0])
    p = {(f, s): s * x for f in range(10) for s in (1, 2, 3)}
    p |= {(f, 4): 3.2 * x for f in range(4, 9)}
    label = stitch_tracklets(p, cut_tracklets(p, 0.5), 3)
    assert len(set(label.values())) == 3
    assert {label[(f, 4)] for f in range(4, 9)} == {label[(0, 3)]}


def test_a_short_piece_takes_the_free_trajectory_of_its_frame():
    """Two bodies at x = 0 and x = 1. At frame 5 body B is seen at x = 0.45 (a mixed
    window), nearer to A's trajectory than to its own; A is held there by its long tracklet,
    so the piece takes B's."""
    x = np.array([1.0, 0.0, 0.0])
    p = {(f, 1): 0 * x for f in range(10)} | {(f, 2): 1 * x for f in range(10)}
    p[(5, 2)] = 0.45 * x
    label = stitch_tracklets(p, cut_tracklets(p, 0.2), 2)
    assert label[(5, 2)] == label[(0, 2)] != label[(5, 1)]
