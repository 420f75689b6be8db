"""Body size: the length that depth errors are quoted against."""

from __future__ import annotations

import math

import pytest
import torch

from netepu.geometry.evaluation import body_length


def test_body_length_known_values():
    """Bipeds: mean height (vertical extent); quadrupeds: mean largest horizontal distance
    between two keypoints, whatever their heights."""
    biped = torch.zeros(2, 3, 3)
    biped[0, :, 2] = torch.tensor([0.1, 1.0, 1.8])
    biped[1, :, 2] = torch.tensor([0.0, 0.5, 1.6])
    biped[0, :, 0] = torch.tensor([0.0, 5.0, -5.0])  # wide arms do not count
    assert body_length(biped, "biped") == pytest.approx((1.7 + 1.6) / 2)
    cow = torch.tensor([[[0.0, 0.0, 0.0], [3.0, 4.0, 9.0], [1.0, 0.0, -9.0]],
                        [[0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [2.0, 0.0, 7.0]]])
    assert body_length(cow, "quadruped") == pytest.approx((5.0 + math.sqrt(8.0)) / 2)
