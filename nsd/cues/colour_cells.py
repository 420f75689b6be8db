"""Colour cells: RGB quantised into ``levels`` per channel, the bins of every colour histogram.

Both colour cues count pixels per cell: the native-resolution masks
(:mod:`nsd.cues.native`) and the individuals' colour models of the mask ownership
(:mod:`nsd.inference.colour_models`).
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["colour_cells"]


def colour_cells(images: Tensor, levels: int) -> Tensor:
    """The cell of every pixel, ``(r * levels + g) * levels + b`` with each channel's level
    ``floor(x * levels)`` (1 in the last level).

    Args:
        images: (..., 3, H, W) in [0, 1]; an 8-bit value v / 255 falls in level
            ``v * levels // 256``.
        levels: per channel.

    Returns:
        (..., H, W) long in [0, levels^3).
    """
    q = (images.clamp(0.0, 1.0) * levels).long().clamp_max(levels - 1)
    return (q[..., 0, :, :] * levels + q[..., 1, :, :]) * levels + q[..., 2, :, :]
