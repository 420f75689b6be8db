r"""Foreground evidence from the background residual: the label-free cue under every other one.

.. math::
    e(x) = \mathrm{clip}\big(\tfrac{\operatorname{mean}_c |I - B| - \tau}{\kappa}, 0, 1\big)

with :math:`B` the per-camera background, :math:`\tau` the ``threshold`` and :math:`\kappa`
the ``softness``. Training weights its pixel loss with it (:mod:`nsd.training.losses`),
proposals and the visual hull are built on it (:mod:`nsd.cues.proposals`,
:mod:`nsd.cues.occupancy`), and inference uses it to sharpen masks.
"""

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
