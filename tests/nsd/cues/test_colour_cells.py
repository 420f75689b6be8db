"""Colour cells (nsd/cues/colour_cells.py): the bins of both colour cues."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.cues.colour_cells import colour_cells


@pytest.mark.parametrize("levels", [2, 8, 16, 32])
def test_every_8_bit_value_falls_in_its_integer_level(levels):
    """v / 255 falls in level v * levels // 256 for all 256 values of every channel (the
    native masks' integer rule of before), and the cell packs the levels as r, g, b."""
    v = np.arange(256)
    rgb = np.stack([v, v[::-1], np.roll(v, 7)], -1)[None].astype(np.uint8)  # (1, 256, 3)
    q = rgb.astype(np.int64) * levels // 256
    expected = (q[..., 0] * levels + q[..., 1]) * levels + q[..., 2]
    cells = colour_cells(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0, levels)
    assert cells.shape == (1, 256)
    assert np.array_equal(cells.numpy(), expected)


def test_batches_and_values_outside_the_unit_range():
    images = torch.tensor([[[[0.0, 1.0, -0.2]], [[0.0, 0.5, 1.3]], [[0.99, 0.0, 0.25]]]])
    cells = colour_cells(images.expand(2, 3, 1, 3), 4)  # (B=2, 3, H=1, W=3)
    # (0, 0, 3), (3, 2, 0), (0, 3, 1): out-of-range values clamp to the first / last level
    assert cells.tolist() == [[[3, 56, 13]]] * 2
