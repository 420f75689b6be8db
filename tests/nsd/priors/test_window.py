"""Weak priors act on batch means per window, with known values."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.priors.window import aspect_prior, position_prior, presence_prior, scale_prior


def test_position_prior_uses_batch_mean_per_window():
    # window 0 at opposite positions over the batch: mean centred -> no penalty
    boxes = torch.tensor(
        [
            [[0.5, 0.5, 0.6, -0.2], [0.5, 0.5, 0.3, 0.0]],
            [[0.5, 0.5, -0.6, 0.2], [0.5, 0.5, 0.3, 0.4]],
        ]
    )
    # window 1 mean centre (0.3, 0.2): 0.13; averaged over 2 windows
    assert position_prior(boxes).item() == pytest.approx(0.13 / 2)


def test_scale_prior():
    boxes = torch.tensor([[[0.2, 0.6, 0, 0]], [[0.4, 0.4, 0, 0]]])  # mean scale 0.4
    assert scale_prior(boxes).item() == pytest.approx(0.0, abs=1e-12)
    assert scale_prior(boxes, target=0.5).item() == pytest.approx(0.01)


def test_aspect_prior_in_pixels():
    boxes = torch.tensor([[[0.2, 0.3, 0, 0]]])  # 1.5 taller than wide on a square image
    assert aspect_prior(boxes, 1.5).item() == pytest.approx(0.0, abs=1e-12)
    # on a 2:1 wide image the same normalised box is 0.75 tall/wide in pixels
    assert aspect_prior(boxes, 1.5, image_size=(100, 200)).item() == pytest.approx(math.log(2) ** 2)


def test_presence_prior_and_gradients():
    p = torch.tensor([[0.9, 0.1], [0.5, 0.5]], requires_grad=True)
    assert presence_prior(p).item() == pytest.approx(0.5)
    presence_prior(p).backward()
    assert torch.allclose(p.grad, torch.full((2, 2), 0.25))
