"""Keypoints of exported subjects: occluders from the other subjects, temporal smoothing."""

from __future__ import annotations

import numpy as np
from pycocotools import mask as mask_utils

from netepu.pipeline.subject_keypoints import _others, smooth_tracks


def _row(image_id: int, subject: int, mask: np.ndarray) -> dict:
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"image_id": image_id, "subject_id": subject, "segmentation": rle}


def test_occluders_are_the_other_subjects_of_the_same_camera_frame():
    a, b, c = (np.zeros((6, 8), bool) for _ in range(3))
    a[1:3, 1:3], b[2:5, 2:6], c[0:2, 5:8] = True, True, True
    rows = {1: [_row(1, 10, a), _row(1, 11, b)], 2: [_row(2, 12, c)]}
    np.testing.assert_array_equal(_others(rows[1][0], rows), b)  # not itself, not image 2
    np.testing.assert_array_equal(_others(rows[1][1], rows), a)
    assert not _others(rows[2][0], rows).any()  # alone in its camera-frame


def test_smoothing_known_values_and_outliers():
    kp = np.zeros((2, 3))
    fits = [(0, 1, kp + 0.0, 0.5), (10, 1, kp + 1.0, 0.5), (20, 1, kp + 2.0, 0.5),
            (10, 2, kp + 7.0, 0.5)]
    same = smooth_tracks(fits, 0)
    for (_, _, k, _), s in zip(fits, same, strict=True):
        np.testing.assert_array_equal(s, k)
    out = smooth_tracks(fits, 10.0)
    w1, w2 = np.exp(-0.5), np.exp(-2.0)  # neighbours 10 and 20 frames away at sigma 10
    np.testing.assert_allclose(out[1], kp + 1.0)  # symmetric neighbours
    np.testing.assert_allclose(out[0], kp + (w1 * 1 + w2 * 2) / (1 + w1 + w2))
    np.testing.assert_allclose(out[3], kp + 7.0)  # another subject is never mixed in
    bad = [(0, 1, kp + 0.0, 0.1), (10, 1, kp + 5.0, 1.0), (20, 1, kp + 0.0, 0.1)]
    assert np.abs(smooth_tracks(bad, 10.0)[1]).max() < 0.3  # a poor fit (10x loss) weighs 1/100
    far = [(0, 1, kp + 0.0, 0.5), (100, 1, kp + 9.0, 0.5)]
    np.testing.assert_allclose(smooth_tracks(far, 10.0)[0], kp)  # beyond 3 sigma: no weight
