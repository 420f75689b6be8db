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



def _episode(swap: bool):
    """A scripted contact episode: A and B apart, then for 5 frames one merged subject (B
    hidden behind A, so A's appearance dominates it), then apart again (on swapped sides
    when ``swap``: only appearance can tell who is who)."""
    frames = [{0: _obs(A, 0), 1: _obs(B, 40)} for _ in range(5)]
    merged = (0.6 * A + 0.4 * B) / np.linalg.norm(0.6 * A + 0.4 * B)
    frames += [{0: _obs(merged, 20)} for _ in range(5)]
    after = {0: _obs(A, 40), 1: _obs(B, 0)} if swap else {0: _obs(A, 0), 1: _obs(B, 40)}
    frames += [after for _ in range(5)]
    return frames


@pytest.mark.parametrize("swap", [False, True])
def test_identity_survives_a_contact_episode(swap):
    trk = SubjectTracker(appearance_weight=0.5, min_similarity=0.3)
    ids = [trk.update(t, subjects) for t, subjects in enumerate(_episode(swap))]
    assert ids[0] == {0: 1, 1: 2}
    assert all(i == {0: 1} for i in ids[5:10])  # the merged subject continues A's track
    assert ids[-1] == {0: 1, 1: 2}  # A and B keep their tracks after the contact


def test_box_overlap_alone_swaps_identities_that_swap_places_in_contact():
    trk = SubjectTracker(appearance_weight=0.0, min_similarity=0.0)
    ids = [trk.update(t, subjects) for t, subjects in enumerate(_episode(True))]
    assert ids[-1] == {0: 2, 1: 1}  # A took B's old box: the stale box decides, wrongly


def _placed(app, x, position):
    return SubjectObservation(app, {"c0": np.array([x, 10.0, 10.0, 20.0])}, np.asarray(position))


def test_position_term_known_values_and_fallback():
    a = _placed(A, 0, [0.0, 0.0, 0.0])
    b = _placed(A, 0, [0.3, 0.4, 0.0])  # 0.5 apart
    assert track_similarity(a, b, 0.5, 0.5, 0.5) == pytest.approx(0.5 + 0.5 * np.exp(-0.5))
    assert track_similarity(a, b, 0.5, 1.0, 0.25) == pytest.approx(np.exp(-2.0))
    # without a position on either side (one camera) the term is left out
    assert track_similarity(a, _obs(A, 0), 0.5, 0.5, 0.5) == pytest.approx(1.0)


def test_positions_keep_identities_where_boxes_and_appearance_cannot():
    """Two look-alikes in a huddle: in frame 1 each one's box sits where the other's was
    (the camera sees them side by side, and they step across each other's place in the
    image) while in the world they stay put. Boxes alone swap them; positions do not."""
    frames = [{0: _placed(A, 0, [0.0, 0.0, 0.0]), 1: _placed(A, 8, [0.5, 0.0, 0.0])},
              {0: _placed(A, 8, [0.02, 0.0, 0.0]), 1: _placed(A, 0, [0.52, 0.0, 0.0])}]
    boxes = SubjectTracker(appearance_weight=0.5, min_similarity=0.0)
    placed = SubjectTracker(appearance_weight=0.5, min_similarity=0.0, position_weight=0.5,
                            position_scale=0.1)
    assert [boxes.update(t, f) for t, f in enumerate(frames)][1] == {0: 2, 1: 1}
    assert [placed.update(t, f) for t, f in enumerate(frames)][1] == {0: 1, 1: 2}


def test_a_track_keeps_its_last_position_through_a_one_camera_frame():
    trk = SubjectTracker(appearance_weight=0.5, min_similarity=0.0, position_weight=0.5,
                         position_scale=0.1)
    trk.update(0, {0: _placed(A, 0, [0.0, 0.0, 0.0])})
    trk.update(1, {0: _obs(A, 0)})  # seen by one camera: no position
    assert trk.tracks[0].last.position is not None
    with pytest.raises(ValueError, match="position_weight"):
        SubjectTracker(position_weight=1.5)


def _flip_frames():
    """Two subjects apart; in frame 2 both look and sit unlike anything before (every link
    below min_similarity), then as in frame 1 again."""
    C = np.array([0.0, 0.0, 1.0])
    steady = {0: _obs(A, 0), 1: _obs(B, 50)}
    odd = {0: _obs(C, 200), 1: _obs(-A, 300)}
    return [steady, steady, odd, steady]


def test_a_full_house_links_the_free_tracks_instead_of_opening_new_ones():
    free = SubjectTracker(appearance_weight=0.5, min_similarity=0.3)
    ids = [free.update(t, f) for t, f in enumerate(_flip_frames())]
    assert ids[2] == {0: 3, 1: 4}  # unbounded: two new tracks while 1 and 2 are live
    bounded = SubjectTracker(appearance_weight=0.5, min_similarity=0.3, max_tracks=2)
    ids = [bounded.update(t, f) for t, f in enumerate(_flip_frames())]
    assert all(set(i.values()) == {1, 2} for i in ids)
    assert bounded.next_id == 3
    assert ids[3] == {0: 1, 1: 2}


def test_tracklets_start_where_a_track_opens_or_is_forced_on():
    trk = SubjectTracker(appearance_weight=0.5, min_similarity=0.3, max_tracks=2)
    pieces = []
    for t, f in enumerate(_flip_frames()):
        trk.update(t, f)
        pieces.append(dict(trk.tracklets))
    assert pieces[0] == pieces[1] == {0: 1, 1: 2}  # opened, then linked above the floor
    assert sorted(pieces[2].values()) == [3, 4]  # both forced on: new tracklets
    # frame 3 looks like frame 1, not like the forced frame 2: forced again
    assert sorted(pieces[3].values()) == [5, 6]
    steady = SubjectTracker(appearance_weight=0.5, min_similarity=0.3, max_tracks=2)
    assert [(steady.update(t, f), steady.tracklets)[1] for t, f in
            enumerate(_flip_frames()[:2])] == [{0: 1, 1: 2}] * 2


def test_the_bound_opens_tracks_below_it_and_beyond_a_crowded_frame():
    trk = SubjectTracker(appearance_weight=1.0, min_similarity=0.5, max_tracks=2)
    assert trk.update(0, {0: _obs(A, 0)}) == {0: 1}
    assert trk.update(1, {0: _obs(B, 0)}) == {0: 2}  # one live track of two: a new one
    assert trk.update(2, {0: _obs(-A, 0)}) in ({0: 1}, {0: 2})  # two live: no third
    C = np.array([0.0, 0.0, 1.0])
    out = trk.update(3, {0: _obs(A, 0), 1: _obs(B, 0), 2: _obs(C, 0)})
    assert sorted(out.values()) == [1, 2, 3]  # more subjects than the bound: the extra opens
    with pytest.raises(ValueError, match="max_tracks"):
        SubjectTracker(max_tracks=0)
