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
