"""Keypoint accuracy of an export's subjects against a synthetic scene
(nsd/evaluation/pose.py): known errors for the true keypoints and their mirror image."""

from __future__ import annotations

import numpy as np

from nsd.evaluation.pose import mirror_errors, subject_frame_errors
from nsd.synth.skeleton import BIPED


def _truth(world) -> dict[int, np.ndarray]:
    """identity -> (T, K, 3) world keypoints of the shared synthetic world."""
    with np.load(world["scene"] / "gt" / "keypoints3d.npz") as z:
        return {int(k.split("_")[1]): z[k] for k in z.files}


def test_mirrored_subjects_are_told_apart_from_fitted_ones(world, tmp_path):
    """Subjects written as the true keypoints score 0 mm, and their left/right swap the
    distance of the two labellings; subjects written mirrored the other way round."""
    truth = _truth(world)
    mirror = list(BIPED.mirror_index())
    frames, sids, kps, expected = [], [], [], []
    for t in range(4):
        for ident, kp in truth.items():
            true, flipped = kp[t], kp[t][mirror]
            apart = 1000 * float(np.linalg.norm(flipped - true, axis=-1).mean())
            frames.append(t)
            sids.append(ident + 1)  # the world's export: subject = identity + 1
            kps.append(flipped if t % 2 else true)
            expected.append((apart, 0.0) if t % 2 else (0.0, apart))
    path = tmp_path / "keypoints3d.npz"
    np.savez(path, subject_frame=np.array(frames), subject_id=np.array(sids),
             subject_keypoints=np.stack(kps).astype(np.float32))
    got = mirror_errors(world["export"], world["scene"], path, mirror)
    assert len(got) == len(expected)
    np.testing.assert_allclose(got, expected, atol=1e-3)  # float32 keypoints: ~1e-4 mm
    assert min(a for a, b in expected if a) > 100  # a body's sides are far apart
    inverted, errors = subject_frame_errors(world["export"], world["scene"], path)
    assert inverted == len(frames)
    np.testing.assert_allclose(errors, [e[0] for e in expected], atol=1e-3)


def test_species_choices_and_keypoints_of_another_body_are_scored_against_the_truth(
        world, tmp_path):
    """The world holds bipeds: subject-frames said to be bipeds are right, quadrupeds wrong,
    and unmatched ones are not scored; a file of another body's keypoints stops the scoring
    unless told that several bodies are fitted, which leaves those subject-frames out."""
    import pytest

    from netepu.pipeline.species_choice import SpeciesChoice
    from nsd.core.errors import ConfigError
    from nsd.evaluation.pose import keypoint_error, species_accuracy

    truth = _truth(world)
    choices = [SpeciesChoice(t, ident + 1, "biped" if t < 3 else "quadruped", {})
               for t in range(4) for ident in truth]
    choices.append(SpeciesChoice(0, 99, "biped", {}))  # no such subject: not scored
    got = species_accuracy(world["export"], world["scene"], choices)
    assert got == {"scored": 4.0 * len(truth), "accuracy": 0.75}
    path = tmp_path / "keypoints3d.npz"
    n = 2 * len(truth)
    np.savez(path, subject_frame=np.repeat([0, 1], len(truth)),
             subject_id=np.tile([i + 1 for i in truth], 2),
             subject_keypoints=np.zeros((n, 25, 3), np.float32))  # a quadruped's 25
    with pytest.raises(ConfigError, match="25 keypoints"):
        keypoint_error(world["export"], world["scene"], path)
    other = keypoint_error(world["export"], world["scene"], path, other_bodies=True)
    assert other["inverted"] == n and other["scored"] == 0 and np.isnan(other["mpjpe_mm"])


def test_scoring_reads_the_ground_truth_of_the_fitted_frames_alone(world, tmp_path, monkeypatch):
    """A file of two frames is scored from those frames' ground truth only, with the errors
    of the matching over every frame; the frames' filter keeps exactly their rows."""
    from nsd.evaluation.identity import ground_truth_identities
    from nsd.evaluation.pose import subject_truth
    from nsd.io.ground_truth import GroundTruth

    every = ground_truth_identities(world["export"], world["scene"])
    assert len({t for _, t, _, _ in every.values()}) > 2  # the world has more frames
    some = ground_truth_identities(world["export"], world["scene"], frames={1, 3})
    assert some == {a: v for a, v in every.items() if v[1] in (1, 3)} and some
    truth = _truth(world)
    frames = np.repeat([1, 3], len(truth))
    sids = np.tile([i + 1 for i in truth], 2)
    kps = np.stack([truth[s - 1][t] + 0.01 * s for t, s in zip(frames, sids, strict=True)])
    path = tmp_path / "keypoints3d.npz"
    np.savez(path, subject_frame=frames, subject_id=sids,
             subject_keypoints=kps.astype(np.float32))
    full = subject_frame_errors(world["export"], world["scene"], path,
                                matched=subject_truth(world["export"], world["scene"]))
    read = []
    original = GroundTruth.frame
    monkeypatch.setattr(GroundTruth, "frame",
                        lambda self, cam, t: read.append(t) or original(self, cam, t))
    assert subject_frame_errors(world["export"], world["scene"], path) == full
    assert set(read) == {1, 3}
    np.testing.assert_allclose(full[1], [1000 * 0.01 * s * 3 ** 0.5 for s in sids], rtol=1e-4)
