"""The hull mask prior: known values, and its gradient pulls each window to its individual."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.priors.mask import hull_mask_prior


def test_known_value_over_owned_pixels_only():
    weights = torch.tensor([[[[0.9, 0.5, 0.3]], [[0.2, 0.5, 0.3]]]])  # (B=1, N=2, 1, 3)
    owners = torch.tensor([[[0, 1, -1]]])  # pixel 2 owned by nobody: not scored
    matching = torch.tensor([[0, 1]])  # window 0 -> individual 0, window 1 -> individual 1
    valid = torch.tensor([[True, True]])
    got = hull_mask_prior(weights, owners, matching, valid)
    # pixel 0: window 0 target 1 (0.9), window 1 target 0 (0.2); pixel 1: 0 (0.5), 1 (0.5)
    px0 = (-math.log(0.9) - math.log(0.8)) / 2
    px1 = (-math.log(0.5) - math.log(0.5)) / 2
    assert got.item() == pytest.approx((px0 + px1) / 2, rel=1e-5)
    # a window matched to an invalid individual targets 0 everywhere
    got = hull_mask_prior(weights, owners, matching, torch.tensor([[True, False]]))
    px1_invalid = (-math.log(0.5) - math.log(0.5)) / 2  # both targets 0 at pixel 1
    px0_invalid = (-math.log(0.9) - math.log(0.8)) / 2
    assert got.item() == pytest.approx((px0_invalid + px1_invalid) / 2, rel=1e-5)
    # nothing owned: zero, with a gradient path
    none = hull_mask_prior(weights.requires_grad_(), torch.full((1, 1, 3), -1), matching, valid)
    assert none.item() == 0.0 and none.requires_grad


def test_gradcheck_float64():
    torch.manual_seed(0)
    w = torch.rand(2, 3, 4, 5, dtype=torch.float64).clamp(0.05, 0.95).requires_grad_()
    owners = torch.randint(-1, 3, (2, 4, 5))
    matching = torch.tensor([[2, 0, 1], [1, 1, 0]])
    valid = torch.tensor([[True, True, False], [True, True, True]])
    assert torch.autograd.gradcheck(lambda x: hull_mask_prior(x, owners, matching, valid), (w,))


def test_descent_moves_each_window_towards_its_individual():
    w = torch.full((1, 2, 2, 2), 0.5, requires_grad=True)
    owners = torch.tensor([[[0, 0], [1, -1]]])
    hull_mask_prior(w, owners, torch.tensor([[1, 0]]), torch.tensor([[True, True]])).backward()
    g = w.grad[0]
    assert (g[0, 1, 0] < 0) and (g[0, 0, 0] > 0)  # window 0 <- individual 1's pixel
    assert (g[1, 0, 0] < 0) and (g[1, 1, 0] > 0)  # window 1 <- individual 0's pixels
    assert g[:, 1, 1].abs().max() == 0  # the unowned pixel gets no gradient
