"""Projection maths against OpenCV, its inverse, and its gradients."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from nsd.cameras.projection import (
    distort_normalized,
    fisheye_lens,
    pixel_to_normalized,
    project_points,
    relative_rotation,
    undistort_normalized,
)
from tests.base import DTYPES, BaseTester


def _points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    return rng.uniform(-1.0, 1.0, (n, 3)) * np.array([1.0, 1.0, 1.2])


class TestProjectPoints(BaseTester):
    def test_equals_cv2_project_points(self, random_cameras):
        rng = np.random.default_rng(0)
        X = _points(rng)
        for cam in random_cameras:
            uv, z = cam.project(X)
            rvec = cv2.Rodrigues(cam.R)[0]
            ref, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, cam.dist if cam.dist.size else None)
            np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-8)
            np.testing.assert_allclose(z, (X @ cam.R.T + cam.t)[:, 2], atol=1e-12)

    @DTYPES
    def test_batched_equals_single(self, random_cameras, dtype):
        X = torch.as_tensor(_points(np.random.default_rng(1), 50), dtype=dtype)
        cams = random_cameras[1:3]  # same distortion length (4 and 5 -> pad)
        K = torch.stack([torch.as_tensor(c.K, dtype=dtype) for c in cams])
        R = torch.stack([torch.as_tensor(c.R, dtype=dtype) for c in cams])
        t = torch.stack([torch.as_tensor(c.t, dtype=dtype) for c in cams])
        d = torch.zeros(2, 5, dtype=dtype)
        for i, c in enumerate(cams):
            d[i, : c.dist.size] = torch.as_tensor(c.dist)
        uv, _ = project_points(X.expand(2, -1, -1), K, R, t, d)
        for i, c in enumerate(cams):
            single, _ = c.project(X.double().numpy())
            self.assert_close(
                uv[i],
                torch.as_tensor(single, dtype=dtype),
                rtol=1e-4,
                atol=1e-3 if dtype == torch.float32 else 1e-8,
            )

    def test_known_value(self):
        K = torch.tensor([[100.0, 0, 50], [0, 200.0, 40], [0, 0, 1]], dtype=torch.float64)
        uv, z = project_points(
            torch.tensor([[0.5, -0.25, 2.0]], dtype=torch.float64),
            K,
            torch.eye(3, dtype=torch.float64),
            torch.zeros(3, dtype=torch.float64),
        )
        self.assert_close(uv, torch.tensor([[75.0, 15.0]], dtype=torch.float64))
        self.assert_close(z, torch.tensor([2.0], dtype=torch.float64))

    def test_gradcheck(self, random_cameras):
        cam = random_cameras[3]
        p = cam.tensors(torch.float64)
        X = torch.as_tensor(_points(np.random.default_rng(2), 5))
        assert self.gradcheck(
            lambda x, K, R, t, d: project_points(x, K, R, t, d)[0],
            [X, p["K"], p["R"], p["t"], p["dist"]],
        )

    @pytest.mark.parametrize("n", [12, 14])
    def test_thin_prism_and_tilted_sensor_equal_cv2(self, n):
        """OpenCV's 12 (thin prism s1..s4) and 14 (tilted sensor tau_x, tau_y) coefficient
        models, projected and undistorted, against cv2.projectPoints / undistortPoints."""
        rng = np.random.default_rng(n)
        dist = np.concatenate([rng.normal(0, 0.03, 12), rng.normal(0, 0.05, n - 12)])
        K = np.array([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]])
        R, t = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], np.array([0.1, -0.1, 3.0])
        X = _points(rng, 100)
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, dist)
        uv, _ = project_points(*(torch.as_tensor(a) for a in (X, K, R, t, dist)))
        np.testing.assert_allclose(uv.numpy(), ref.reshape(-1, 2), rtol=0, atol=1e-8)
        back = pixel_to_normalized(uv, torch.as_tensor(K), torch.as_tensor(dist))
        ref_back = cv2.undistortPoints(
            ref, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        ).reshape(-1, 2)
        # both invert by fixed-point iteration (ours: 20 steps, ~1e-5 px here)
        np.testing.assert_allclose(back.numpy(), ref_back, rtol=0, atol=1e-7)

    def test_bad_distortion_size_raises(self):
        with pytest.raises(ValueError, match="distortion has 3 coefficients"):
            distort_normalized(torch.zeros(1, 2), torch.zeros(3))


class TestUndistort(BaseTester):
    @pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
    def test_inverts_distortion(self, n):
        rng = np.random.default_rng(n)
        dist = torch.as_tensor(rng.normal(0, 0.03, n))
        xy = torch.as_tensor(rng.uniform(-0.6, 0.6, (100, 2)))
        back = undistort_normalized(distort_normalized(xy, dist), dist, iterations=100)
        self.assert_close(back, xy, atol=1e-9)

    def test_pixel_to_normalized_equals_cv2(self, random_cameras):
        rng = np.random.default_rng(3)
        for cam in random_cameras:
            uv = rng.uniform([20, 20], [300, 220], (50, 2))
            ref = cv2.undistortPoints(
                uv.reshape(-1, 1, 2),
                cam.K,
                cam.dist if cam.dist.size else None,
                None,
                None,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
            ).reshape(-1, 2)
            p = cam.tensors(torch.float64)
            ours = pixel_to_normalized(torch.as_tensor(uv), p["K"], p["dist"]).numpy()
            np.testing.assert_allclose(ours, ref, atol=1e-7)

    def test_unproject_inverts_project(self, random_cameras):
        X = _points(np.random.default_rng(4))
        for cam in random_cameras:
            uv, z = cam.project(X)
            np.testing.assert_allclose(cam.unproject(uv, z), X, atol=1e-7)
            rays = cam.unproject(uv)
            expected = (X - cam.center) / np.linalg.norm(X - cam.center, axis=1, keepdims=True)
            np.testing.assert_allclose(rays, expected, atol=1e-7)


class TestRelativeRotation(BaseTester):
    def test_maps_point_seen_by_v_to_same_point_seen_by_w(self, random_cameras):
        X = _points(np.random.default_rng(5))
        for a in random_cameras:
            for b in random_cameras:
                Rab = relative_rotation(torch.as_tensor(a.R), torch.as_tensor(b.R)).numpy()
                Xa, Xb = X @ a.R.T + a.t, X @ b.R.T + b.t
                # points: rotation plus the relative translation t_b - R_ab t_a
                np.testing.assert_allclose(Xa @ Rab.T + (b.t - Rab @ a.t), Xb, atol=1e-10)
                # directions (what NSD rotates its latent cloud with): rotation only
                d = X[1:] - X[:-1]
                np.testing.assert_allclose((d @ a.R.T) @ Rab.T, d @ b.R.T, atol=1e-10)

    def test_identity_and_inverse(self, random_cameras):
        a, b = (torch.as_tensor(c.R) for c in random_cameras[:2])
        self.assert_close(relative_rotation(a, a), torch.eye(3, dtype=torch.float64))
        self.assert_close(
            relative_rotation(a, b) @ relative_rotation(b, a), torch.eye(3, dtype=torch.float64)
        )


def test_fisheye_projection_gradcheck_and_inverse():
    """Kannala-Brandt through the lens vector: float64 gradcheck of the projection, and the
    Newton inverse undoing it."""
    g = torch.Generator().manual_seed(3)
    pts = (torch.rand(2, 7, 3, generator=g, dtype=torch.float64) - 0.5) * 2
    pts[..., 2] = pts[..., 2].abs() + 1.0
    K = torch.tensor([[300.0, 0, 160], [0, 310, 120], [0, 0, 1]], dtype=torch.float64)
    lens = fisheye_lens(torch.tensor([[-0.05, 0.01, -0.002, 0.0004], [0.1, -0.02, 0.0, 0.0]],
                                     dtype=torch.float64)).requires_grad_(True)
    R, t = torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, d: project_points(p, K, R, t, d)[0], (pts, lens))
    xy = pts[..., :2] / pts[..., 2:]
    back = undistort_normalized(distort_normalized(xy, lens), lens)
    torch.testing.assert_close(back, xy, atol=1e-10, rtol=0)
    assert not torch.allclose(distort_normalized(xy, lens), xy)  # it does distort
