"""Focal spatial transformer: bump values, zero edge, crop/paste round trip, gradients."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from nsd.model.focal_st import (
    axis_grid,
    box_to_pixels,
    box_to_theta,
    crop,
    focal_bump,
    focal_bump_at,
    inverse_theta,
    paste,
)
from tests.base import DTYPES, BaseTester


class TestBump(BaseTester):
    @pytest.mark.parametrize(
        ("x", "expected"), [(0.0, 1.0), (0.5, 0.7165), (0.8, 0.1690), (0.95, 9.54e-5)]
    )
    def test_known_values(self, x, expected):
        g = focal_bump_at(
            torch.tensor(x, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
        )
        assert g.item() == pytest.approx(expected, rel=2e-3)

    def test_zero_on_and_outside_edge(self):
        xs = torch.tensor([1.0, 1.2, -1.0, 0.0, 2.0])
        ys = torch.tensor([0.0, 0.0, 0.0, 1.0, 2.0])
        assert torch.equal(focal_bump_at(xs, ys), torch.zeros(5))
        # the corner (1, 1) where the raw formula would give ~30
        assert focal_bump_at(torch.tensor(1.0), torch.tensor(1.0)).item() == 0.0
        on_edge = torch.tensor(0.5**0.25)  # x^4 + y^4 = 1 exactly: r = 1
        assert focal_bump_at(on_edge, on_edge).item() == 0.0

    def test_smooth_to_zero_and_symmetric(self):
        g = focal_bump(32, 32, dtype=torch.float64)
        assert g.max() <= 1.0 and g.min() >= 0.0
        self.assert_close(g, g.flip(0))
        self.assert_close(g, g.t())
        row = focal_bump_at(
            torch.linspace(0.9, 0.999, 50, dtype=torch.float64),
            torch.zeros(50, dtype=torch.float64),
        )
        assert (row[1:] <= row[:-1]).all() and row[-1] < 1e-100

    def test_cached_grid_matches_the_formula_and_is_not_shared(self):
        g = focal_bump(6, 10, dtype=torch.float64)
        ys = (2 * torch.arange(6, dtype=torch.float64) + 1) / 6 - 1
        xs = (2 * torch.arange(10, dtype=torch.float64) + 1) / 10 - 1
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        assert torch.equal(g, focal_bump_at(gx, gy))
        g.zero_()  # the caller owns its tensor: the cache is untouched
        assert torch.equal(focal_bump(6, 10, dtype=torch.float64), focal_bump_at(gx, gy))

    def test_gradient_finite_at_edge(self):
        x = torch.tensor([0.999, 1.0, 1.5, 0.0], dtype=torch.float64, requires_grad=True)
        focal_bump_at(x, torch.zeros(4, dtype=torch.float64)).sum().backward()
        assert torch.isfinite(x.grad).all()


class TestCropPaste(BaseTester):
    def test_paste_of_crop_returns_image_inside_window(self):
        g = torch.Generator().manual_seed(0)
        img = torch.rand(1, 3, 32, 32, generator=g, dtype=torch.float64)
        boxes = torch.tensor([[[0.5, 0.5, 0.0, 0.0]]], dtype=torch.float64)
        # the window covers pixels [8, 24)^2; a 16x16 crop samples exactly their centres
        c = crop(img, boxes, (16, 16), focal=False)
        self.assert_close(c[0, 0], img[0, :, 8:24, 8:24])
        back = paste(c, boxes, (32, 32), focal=False, padding_mode="zeros")
        self.assert_close(back[0, 0, :, 8:24, 8:24], img[0, :, 8:24, 8:24])
        assert back[0, 0, :, :6].abs().max() == 0  # zero padding outside the window

    def test_focal_round_trip_is_bump_weighted(self):
        img = torch.rand(1, 1, 24, 24, dtype=torch.float64)
        boxes = torch.tensor([[[1.0, 1.0, 0.0, 0.0]]], dtype=torch.float64)
        c = crop(img, boxes, (24, 24), focal=True)
        G = focal_bump(24, 24, dtype=torch.float64)
        self.assert_close(c[0, 0, 0], img[0, 0] * G)
        back = paste(c, boxes, (24, 24), focal=True)
        self.assert_close(back[0, 0, 0], img[0, 0] * G * G)

    @DTYPES
    def test_shapes_and_gradients(self, dtype):
        img = torch.rand(2, 3, 20, 30, dtype=dtype)
        boxes = torch.tensor([[[0.4, 0.6, 0.1, -0.2], [0.2, 0.3, -0.5, 0.5]]] * 2, dtype=dtype)
        c = crop(img, boxes, (12, 8))
        assert c.shape == (2, 2, 3, 12, 8)
        p = paste(c, boxes, (20, 30), padding_mode="border")
        assert p.shape == (2, 2, 3, 20, 30)
        if dtype == torch.float64:
            # generic box values: bilinear sampling has kinks where samples hit pixel centres
            generic = torch.tensor(
                [[[0.4137, 0.6071, 0.1213, -0.2377], [0.2291, 0.3133, -0.5179, 0.4923]]] * 2,
                dtype=dtype,
            )
            assert self.gradcheck(
                lambda b: paste(crop(img, b, (6, 6)), b, (20, 30)).sum(), [generic], atol=1e-4
            )

    def test_box_to_pixels(self):
        px = box_to_pixels(torch.tensor([[0.5, 0.25, 0.0, -0.5]]), (40, 80))
        self.assert_close(px, torch.tensor([[20.0, 5.0, 40.0, 10.0]]))


class TestAxisGrid(BaseTester):
    """The separable grid against torch's affine_grid (its batched-product reference)."""

    @staticmethod
    def _boxes(m: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(3)
        s = 0.2 + torch.rand(m, 2, generator=g, dtype=torch.float64)
        t = 2 * torch.rand(m, 2, generator=g, dtype=torch.float64) - 1
        return torch.cat([s, t], 1)  # (m, 4) = (sx, sy, tx, ty)

    @pytest.mark.parametrize("size", [(5, 7), (32, 32), (1, 3)])
    def test_equals_affine_grid(self, size):
        boxes = self._boxes(4)
        for theta in (box_to_theta(boxes), inverse_theta(boxes)):  # crop and paste-back
            ref = F.affine_grid(theta, [4, 1, *size], align_corners=False)
            self.assert_close(axis_grid(theta, size), ref, rtol=0, atol=1e-13)

    def test_gradient_equals_affine_grids(self):
        theta = box_to_theta(self._boxes(3)).requires_grad_()
        w = torch.randn(3, 4, 6, 2, dtype=torch.float64)
        (axis_grid(theta, (4, 6)) * w).sum().backward()
        ours, theta.grad = theta.grad, None
        (F.affine_grid(theta, [3, 1, 4, 6], align_corners=False) * w).sum().backward()
        keep = torch.tensor([[1.0, 0, 1], [0, 1, 1]], dtype=torch.float64)  # the read terms
        self.assert_close(ours, theta.grad * keep, rtol=0, atol=1e-12)

    def test_gradcheck(self):
        theta = box_to_theta(self._boxes(2)).requires_grad_()
        assert torch.autograd.gradcheck(lambda t: axis_grid(t, (3, 5)), (theta,))
