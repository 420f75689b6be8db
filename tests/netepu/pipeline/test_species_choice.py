"""Which species each subject is: the fit of lowest silhouette loss, voted along the track."""

from __future__ import annotations

import numpy as np
import pytest

from netepu.pipeline.species_choice import (
    SpeciesChoice,
    choose_species,
    read_species_csv,
    species_of_rows,
    split_fits,
    write_species_csv,
)
from nsd.io.keypoints import SubjectKeypoints

K = {"biped": 4, "quadruped": 6}  # keypoints per body


def _write(path, species, losses):
    """A keypoints3d.npz of ``losses`` {(frame, subject): loss}, two rows per subject-frame
    (ids 100 * frame + 10 * subject + camera), keypoints filled with the loss."""
    fitted = SubjectKeypoints()
    for (t, sid), loss in sorted(losses.items()):
        rows = [{"id": 100 * t + 10 * sid + c} for c in range(2)]
        fitted.add(t, sid, rows, np.full((K[species], 3), loss), loss)
    path.parent.mkdir(parents=True, exist_ok=True)
    fitted.save(path, K[species])
    return path


def test_each_subject_frame_takes_the_body_that_fits_it_and_one_bad_frame_is_outvoted(tmp_path):
    # subject 1 fits the biped better on frames 0-40 but on frame 20 (a poor mask);
    # subject 2 is a quadruped throughout; frame 50 of subject 1 is fitted by one body only
    biped = {(t, 1): 0.1 for t in (0, 10, 30, 40)} | {(20, 1): 0.5, (50, 1): 0.1}
    biped |= {(t, 2): 0.4 for t in (0, 10, 20)}
    quad = {(t, 1): 0.3 for t in (0, 10, 30, 40)} | {(20, 1): 0.2}
    quad |= {(t, 2): 0.15 for t in (0, 10, 20)}
    fits = {"biped": _write(tmp_path / "b.npz", "biped", biped),
            "quadruped": _write(tmp_path / "q.npz", "quadruped", quad)}
    alone = {(c.frame, c.subject_id): c.species for c in choose_species(fits, window=0)}
    assert alone[(20, 1)] == "quadruped" and alone[(10, 1)] == "biped"
    assert (50, 1) not in alone  # not fitted by every body: no choice
    voted = choose_species(fits)
    got = {(c.frame, c.subject_id): c.species for c in voted}
    assert got == {**{(t, 1): "biped" for t in (0, 10, 20, 30, 40)},
                   **{(t, 2): "quadruped" for t in (0, 10, 20)}}
    assert voted[0].losses == pytest.approx({"biped": 0.1, "quadruped": 0.3})
    # a track that swaps bodies for good follows the swap after its window
    swap = {(t, 3): 0.1 for t in range(0, 60, 10)}
    other = {(t, 3): (0.3 if t < 30 else 0.05) for t in range(0, 60, 10)}
    fits = {"biped": _write(tmp_path / "b2.npz", "biped", swap),
            "quadruped": _write(tmp_path / "q2.npz", "quadruped", other)}
    got = [c.species for c in choose_species(fits, window=1)]
    assert got == ["biped"] * 3 + ["quadruped"] * 3
    # track 4 a biped at frame 0, then forced onto a quadruped (tracklets 7 and 8): voted
    # along the track the biped's one frame is outvoted, along its tracklet it is not
    biped = {(t, 4): (0.1 if t == 0 else 0.4) for t in range(0, 60, 10)}
    quad = {(t, 4): (0.3 if t == 0 else 0.1) for t in range(0, 60, 10)}
    fits = {"biped": _write(tmp_path / "b3.npz", "biped", biped),
            "quadruped": _write(tmp_path / "q3.npz", "quadruped", quad)}
    assert choose_species(fits, window=2)[0].species == "quadruped"
    pieces = {(t, 4): 7 if t == 0 else 8 for t in range(0, 60, 10)}
    got = [c.species for c in choose_species(fits, window=2, tracklets=pieces)]
    assert got == ["biped"] + ["quadruped"] * 5


def test_each_species_file_keeps_the_subject_frames_that_took_it(tmp_path):
    biped = {(0, 1): 0.1, (0, 2): 0.4, (10, 1): 0.1, (10, 2): 0.4}
    quad = {(0, 1): 0.3, (0, 2): 0.2, (10, 1): 0.3, (10, 2): 0.2}
    fits = {"biped": _write(tmp_path / "b.npz", "biped", biped),
            "quadruped": _write(tmp_path / "q.npz", "quadruped", quad)}
    choices = choose_species(fits)
    out = {s: tmp_path / s / "keypoints3d.npz" for s in fits}
    assert split_fits(fits, choices, out) == {"biped": 2, "quadruped": 2}
    with np.load(out["biped"]) as z:
        assert z["subject_id"].tolist() == [1, 1] and z["subject_frame"].tolist() == [0, 10]
        assert z["id"].tolist() == [10, 11, 1010, 1011]  # the two rows of each, in order
        assert z["keypoints"].shape == (4, 4, 3) and np.allclose(z["keypoints"], 0.1)
    with np.load(out["quadruped"]) as z:
        assert z["id"].tolist() == [20, 21, 1020, 1021]
        assert z["subject_keypoints"].shape == (2, 6, 3) and np.allclose(z["keypoints"], 0.2)
        assert z["subject_views"].tolist() == [2, 2]


def test_every_row_takes_the_species_of_its_tracks_nearest_fitted_frame(tmp_path):
    choices = [SpeciesChoice(0, 1, "biped", {}), SpeciesChoice(20, 1, "quadruped", {}),
               SpeciesChoice(10, 2, "quadruped", {})]
    sid = np.array([1, 1, 1, 1, 1, 2, 2, 3])
    frame = np.array([0, 9, 10, 11, 30, 0, 99, 5])
    got = species_of_rows(sid, frame, choices)
    # frame 10 is halfway: the earlier fitted frame; track 3 was never fitted
    assert got.tolist() == ["biped", "biped", "biped", "quadruped", "quadruped",
                            "quadruped", "quadruped", ""]
    # track 1 cut at frame 11 into tracklets 7 and 8 (a forced link): the same as by the
    # track (frame 10 is in 7, with the biped's fit); cut at frame 10, frame 10 takes the
    # quadruped of its own tracklet's frame 20; track 3's tracklet has no fit: ""
    sid, frame = np.append(sid, 1), np.append(frame, 20)  # the fitted frame's own row
    piece = np.array([7, 7, 7, 8, 8, 9, 9, 10, 8])
    assert species_of_rows(sid, frame, choices, piece).tolist() == [*got.tolist(), "quadruped"]
    cut = np.array([7, 7, 8, 8, 8, 9, 9, 10, 8])  # the cut at frame 10 instead
    assert species_of_rows(sid, frame, choices, cut)[2] == "quadruped"  # not track 1's biped
    path = tmp_path / "species.csv"
    choices[0] = SpeciesChoice(0, 1, "biped", {"biped": 0.125, "quadruped": 0.5})
    write_species_csv(path, choices[:1])
    assert read_species_csv(path) == choices[:1]


def test_identities_are_assigned_within_each_species(tmp_path):
    """Two bipeds (tracks 1, 2) and two quadrupeds (tracks 3, 4): each species' texture model
    gives codes in its own space, here the same two codes for both species. Assigned within
    each species, the four get four identities (two per species, the quadrupeds numbered
    after the bipeds) and every track keeps one; one k-means over all four would have two
    codes for four individuals."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from netepu.pipeline.stages import _identities_of_species
    from nsd.io.embeddings import EmbeddingWriter

    frames = np.repeat(np.arange(10), 4)
    sid = np.tile([1, 2, 3, 4], 10)
    ids = np.arange(len(sid)) + 1
    cams = np.array(["cam0"] * len(sid), object)
    body = {1: "biped", 2: "biped", 3: "quadruped", 4: "quadruped"}
    code = {1: [1.0, 0.1], 2: [0.1, 1.0], 3: [1.0, 0.1], 4: [0.1, 1.0]}
    keys = {"id": ids, "camera": cams, "frame": frames, "subject_id": sid}
    (tmp_path / "export").mkdir()
    w = EmbeddingWriter(tmp_path / "export" / "embeddings")
    w.write(keys | {"app": np.zeros((len(sid), 3), np.float32)})
    w.close()
    coded = frames % 5 == 0  # keypoints, hence codes, on every 5th frame
    for s in ("biped", "quadruped"):
        (tmp_path / "texture" / s).mkdir(parents=True)
        mine = coded & np.array([body[x] == s for x in sid])
        vec = np.array([code[x] for x in sid], np.float32)
        vec[~mine] = np.nan
        w = EmbeddingWriter(tmp_path / "texture" / s / "embeddings")
        w.write(keys | {"texture_reid": vec})
        w.close()
    (tmp_path / "keypoints").mkdir()
    write_species_csv(tmp_path / "keypoints" / "species.csv",
                      [SpeciesChoice(t, x, body[x], {}) for t in (0, 5) for x in (1, 2, 3, 4)])
    up = {name: SimpleNamespace(folder=tmp_path / name)
          for name in ("export", "texture", "keypoints")}
    i = OmegaConf.create({"fill": "nearest", "method": "subjects", "restarts": 10, "k": 0})
    table, identity, summary = _identities_of_species(up, ["quadruped", "biped"], "texture_reid",
                                                      i)
    assert table["id"].tolist() == ids.tolist()
    per_track = {x: set(identity[sid == x].tolist()) for x in (1, 2, 3, 4)}
    assert all(len(v) == 1 for v in per_track.values())
    assert {*per_track[1], *per_track[2]} == {0, 1} and {*per_track[3], *per_track[4]} == {2, 3}
    assert summary["identities"] == 4
    assert summary["species"]["biped"]["k"] == summary["species"]["quadruped"]["k"] == 2
    assert summary["species"]["quadruped"]["first_identity"] == 2


def test_keypoint_files_of_the_formats_stage_take_the_species_skeleton_when_it_fits(tmp_path):
    """The formats stage names the keypoints by their species' skeleton (names and bones)
    when the file holds that species' keypoints; keypoints of another count (the pose
    regressor's, from a user's labels) and models of no known species keep ``kp0``.."""
    from netepu.pipeline.stages import _keypoint_file
    from nsd.synth.skeleton import BIPED, QUADRUPED

    for k, folder in ((BIPED.num_keypoints, "a"), (5, "b")):
        (tmp_path / folder).mkdir()
        np.savez(tmp_path / folder / "keypoints3d.npz", id=np.arange(2),
                 keypoints=np.zeros((2, k, 3)))
    named = _keypoint_file(tmp_path / "a", "biped")
    assert named.skeleton == "biped" and named.nodes == BIPED.keypoint_names
    assert named.edges == BIPED.skeleton and named.path == tmp_path / "a" / "keypoints3d.npz"
    other = _keypoint_file(tmp_path / "b", "biped")  # 5 keypoints are not a biped's
    assert other.skeleton == "biped" and other.nodes == () and other.edges == ()
    assert _keypoint_file(tmp_path / "a", "quadruped").nodes == ()  # counts differ
    assert QUADRUPED.num_keypoints != BIPED.num_keypoints
    unknown = _keypoint_file(tmp_path / "a", "")  # a checkpoint of the user's own
    assert unknown.skeleton == "subject" and unknown.nodes == ()
