"""Training points: true boundary sampling, far points in the region, in-mask points."""

from __future__ import annotations

import numpy as np
import pytest

from netepu.geometry.sampling import (
    boundary_pixels,
    sample_foreground_points,
    sample_silhouette_points,
)


def _disc(h=60, w=80, r=15):
    yy, xx = np.mgrid[:h, :w]
    return (xx - 40) ** 2 + (yy - 30) ** 2 < r * r


def test_boundary_pixels_known():
    m = np.zeros((4, 5), bool)
    m[1:3, 1:3] = True
    b = {tuple(p) for p in boundary_pixels(m)}
    # every foreground pixel of a 2x2 square and its 8 outer 4-neighbours
    assert {(1, 1), (2, 1), (1, 2), (2, 2)} <= b
    assert {(0, 1), (3, 1), (1, 0), (1, 3)} <= b
    assert (0, 0) not in b and len(b) == 12
    assert len(boundary_pixels(np.zeros((3, 3), bool))) == 0
    assert len(boundary_pixels(np.ones((3, 3), bool))) == 0


def test_near_points_straddle_the_boundary():
    m = _disc()
    rng = np.random.default_rng(0)
    uv, label = sample_silhouette_points(m, 2000, 0, rng, sigma_near=1.0)
    dist = np.hypot(uv[:, 0] - 40, uv[:, 1] - 30)
    assert np.all(np.abs(dist - 15) < 6)  # within a few pixels of the contour
    assert 0.35 < label.mean() < 0.65  # both sides
    assert np.array_equal(label, m[uv[:, 1].astype(int), uv[:, 0].astype(int)])
    assert np.all(uv == np.round(uv))  # pixel centres: exact labels


def test_far_points_stay_in_region():
    m = _disc()
    region = np.zeros_like(m)
    region[5:55, 10:70] = True
    rng = np.random.default_rng(1)
    uv, label = sample_silhouette_points(m, 10, 3000, rng, region=region)
    far = uv[10:].astype(int)
    assert region[far[:, 1], far[:, 0]].all()
    # uniform in the region: the foreground share matches the area share
    share = m[region].mean()
    assert abs(label[10:].mean() - share) < 0.03


def test_no_boundary_falls_back():
    rng = np.random.default_rng(2)
    uv, label = sample_silhouette_points(np.zeros((10, 10), bool), 5, 5, rng)
    assert uv.shape == (10, 2) and not label.any()


def test_foreground_points():
    m = _disc()
    uv = sample_foreground_points(m, 500, np.random.default_rng(3)).astype(int)
    assert m[uv[:, 1], uv[:, 0]].all()
    with pytest.raises(ValueError, match="empty"):
        sample_foreground_points(np.zeros((4, 4), bool), 3, np.random.default_rng(0))


def test_deterministic_given_rng():
    m = _disc()
    a = sample_silhouette_points(m, 50, 50, np.random.default_rng(5))
    b = sample_silhouette_points(m, 50, 50, np.random.default_rng(5))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
