"""TODO docstring."""

from __future__ import annotations

from torch import Tensor

__all__ = ["foreground_evidence"]


def foreground_evidence(
    images: Tensor, backgrounds: Tensor, threshold: float = 0.04, softness: float = 0.08
) -> Tensor:
    """Soft foreground evidence :math:`e \\in [0, 1]` from the background residual.

    Args:
        images, backgrounds: (B, 3, H, W) in [0, 1].
        threshold: residual below which a pixel is background (codec/shading noise).
        softness: residual range over which evidence rises from 0 to 1.

    Returns:
        (B, H, W).
    """
    r = (images - backgrounds).abs().mean(1)
    return ((r - threshold) / softness).clamp(0.0, 1.0)
