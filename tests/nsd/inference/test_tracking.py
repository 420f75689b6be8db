"""Subject tracks: ids follow appearance and boxes, not the per-frame association ids."""

from __future__ import annotations

import numpy as np
import pytest

from nsd.inference.tracking import SubjectObservation, SubjectTracker, track_similarity

A, B = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])


def _obs(app, x):
    return SubjectObservation(app, {"c0": np.array([x, 10.0, 10.0, 20.0])})


def test_similarity_known_values():
    assert track_similarity(_obs(A, 0), _obs(A, 0), 0.5) == pytest.approx(1.0)
    assert track_similarity(_obs(A, 0), _obs(B, 0), 0.5) == pytest.approx(0.5)  # IoU 1, cos 0
    assert track_similarity(_obs(A, 0), _obs(A, 5), 0.0) == pytest.approx(1 / 3)  # IoU 50/150
    no_common = SubjectObservation(A, {"c1": np.array([0.0, 10.0, 10.0, 20.0])})
    assert track_similarity(_obs(A, 0), no_common, 0.5) == pytest.approx(0.5)


def test_ids_survive_swapped_association_ids():
    trk = SubjectTracker(appearance_weight=0.5, min_similarity=0.3)
    first = trk.update(0, {0: _obs(A, 0), 1: _obs(B, 50)})
    assert first == {0: 1, 1: 2}
    # the association numbers the subjects the other way round in the next frame
    second = trk.update(1, {0: _obs(B, 52), 1: _obs(A, 1)})
    assert second == {0: 2, 1: 1}


def test_dissimilar_subject_opens_a_track_and_gaps_close_tracks():
    trk = SubjectTracker(appearance_weight=1.0, min_similarity=0.5, max_gap=2)
    assert trk.update(0, {0: _obs(A, 0)}) == {0: 1}
    assert trk.update(1, {0: _obs(B, 0)}) == {0: 2}  # cos 0 < 0.5: new track
    assert trk.update(2, {0: _obs(A, 0)}) == {0: 1}  # unseen for 2 frames: still open
    assert trk.update(5, {0: _obs(A, 0)}) == {0: 3}  # unseen for 3 > max_gap: closed
    assert trk.update(6, {}) == {}
