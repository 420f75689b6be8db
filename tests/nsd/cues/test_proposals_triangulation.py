"""Label-free proposals from residual evidence, and multi-view triangulation of windows."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.cameras.calibration import CameraRig
from nsd.cues.proposals import evidence_proposals
from nsd.cues.triangulation import ray_distances, triangulate_midpoints, window_rays
from nsd.priors.depth import depth_prior
from nsd.priors.proposal import proposal_prior
from tests.base import BaseTester
from tests.conftest import look_at_camera


def _blob(H, W, cx, cy, hw, hh):
    e = torch.zeros(H, W)
    e[cy - hh : cy + hh, cx - hw : cx + hw] = 1.0
    return e


class TestProposals(BaseTester):
    def test_two_separate_blobs(self):
        ev = (_blob(64, 64, 16, 32, 4, 12) + _blob(64, 64, 48, 30, 4, 12))[None]
        boxes, valid = evidence_proposals(ev, 2, min_scale=0.05)
        assert valid.all()
        centres = sorted(boxes[0, :, 2].tolist())
        # pixel 16 -> normalised (2 * 16 + 1) / 64 - 1 = -0.484 (blob centre at x = 15.5 -> -0.5)
        assert centres[0] == pytest.approx(-0.5, abs=0.02)
        assert centres[1] == pytest.approx(0.5, abs=0.02)
        # a uniform blob of half-height 12 px (0.375): 2 sigma / fill = 0.375 * 2 / sqrt(3) / 0.75
        sy = boxes[0, :, 1]
        assert torch.allclose(sy, torch.full_like(sy, 0.375 * 2 / 3**0.5 / 0.75), atol=0.02)

    def test_empty_frame_invalid(self):
        boxes, valid = evidence_proposals(torch.zeros(1, 32, 32), 2)
        assert not valid.any() and torch.isfinite(boxes).all()

    def test_prior_zero_at_proposals_and_permutation_invariant(self):
        props = torch.tensor([[[0.3, 0.5, -0.4, 0.0], [0.25, 0.6, 0.5, 0.1]]])
        valid = torch.ones(1, 2, dtype=torch.bool)
        assert proposal_prior(props.flip(1), props, valid).item() == pytest.approx(0, abs=1e-12)
        boxes = props.clone().requires_grad_(True)
        moved = boxes + torch.tensor([0.0, 0.0, 0.1, 0.0])
        assert proposal_prior(moved, props, valid).item() == pytest.approx(0.01, rel=1e-5)
        proposal_prior(moved, props, valid).backward()
        assert torch.isfinite(boxes.grad).all()
        assert proposal_prior(moved, props, torch.zeros_like(valid)).item() == 0.0


class TestTriangulation(BaseTester):
    def _rig(self):
        return CameraRig(
            [
                look_at_camera("a", np.array([4.0, 0, 1.5]), f=100, size=(128, 128)),
                look_at_camera("b", np.array([0, 4.0, 1.5]), f=100, size=(128, 128)),
            ]
        )

    def _windows_at(self, cam, X):
        uv, _ = cam.project(X)
        t = (uv + 0.5) / 64 - 1  # pixel -> normalised centre (W = H = 128)
        return torch.tensor([[[0.3, 0.3, *p] for p in t]], dtype=torch.float64)

    def test_window_rays_and_midpoints_recover_points(self):
        rig = self._rig()
        X = np.array([[0.2, -0.3, 0.9], [-0.5, 0.4, 1.2]])
        st = rig.stacked(torch.float64)
        ca = st[0:1]
        cb = st[1:2]
        o1, d1 = window_rays(self._windows_at(rig[0], X), image_size=(128, 128), **ca.as_dict())
        o2, d2 = window_rays(self._windows_at(rig[1], X), image_size=(128, 128), **cb.as_dict())
        P, ok = triangulate_midpoints(o1, d1, o2, d2)
        assert ok.all()
        self.assert_close(P[0], torch.as_tensor(X), atol=1e-9)
        D = ray_distances(o1, d1, o2, d2)[0]
        assert D[0, 0] < 1e-9 and D[1, 1] < 1e-9 and D[0, 1] > 0.05 and D[1, 0] > 0.05

    def test_parallel_rays_invalid(self):
        o = torch.zeros(1, 3)
        d = torch.tensor([[[0.0, 0.0, 1.0]]])
        _, ok = triangulate_midpoints(o, d, o + torch.tensor([[1.0, 0, 0]]), d)
        assert not ok.any()
        dist = ray_distances(o, d, o + torch.tensor([[1.0, 0, 0]]), d)
        assert dist.item() == pytest.approx(1.0)

    def test_depth_prior_relative(self):
        z = torch.tensor([[0.0, 1.0]], requires_grad=True)
        D = torch.tensor([[4.0, 4.3]])  # 0.3 m apart -> one unit apart
        ok = torch.ones(1, 2, dtype=torch.bool)
        assert depth_prior(z, D, ok, unit=0.3).item() == pytest.approx(0.0, abs=1e-10)
        assert depth_prior(z + 5.0, D, ok, unit=0.3).item() == pytest.approx(0.0, abs=1e-10)
        wrong = depth_prior(z.flip(1), D, ok, unit=0.3)
        assert wrong.item() == pytest.approx(1.0)  # each window off by 1 unit
        assert (
            depth_prior(z, D, torch.tensor([[True, False]])).item() == 0.0
        )  # one window: no order
