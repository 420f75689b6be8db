r"""Per-window mask normalisation: every window must stay visible.

The reference code divides each decoded window mask by its own maximum (floor
1e-4), so that a window cannot switch itself off by decoding an empty mask:

.. math:: \tilde m = m / \max(\max_{x} m(x), \epsilon).

With the focal spatial transformer that is not enough. The pasted mask is
:math:`G \cdot \tilde m` (the bump :math:`G` is 0 on and outside its edge), so a
decoder can put its maximum where :math:`G \approx 0`, at the crop's border, and
the pasted window is empty again: the re-synthesised view shows only the
background, the boxes get no image gradient, and training stays there (measured:
6 of 9 fifteen-minute runs, docs/nsd.md). Without the bump the same escape is a
one-pixel peak.

``"visible"`` normalises by the maximum of what is pasted, locally averaged:

.. math::
    s = \max_x \big(\mathrm{avgpool}_k (G \cdot m)\big)(x), \qquad
    \tilde m = m / \max(s, \epsilon),

with :math:`G = 1` for the classical transformer. The pasted mask
:math:`G \tilde m` then peaks at exactly 1 for :math:`k = 1` and at 1 or more
(the paste clamps it to 1) for :math:`k > 1`, wherever the decoder puts its
mass: a mask hidden under the bump's edge is scaled up until its visible part is
opaque, and a peak narrower than :math:`k \times k` pixels is scaled up by up to
:math:`k^2`, which makes its neighbourhood visible too. :math:`\tilde m` itself
may exceed 1 where :math:`G < 1`; only the pasted mask is a mask.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from nsd.model.focal_st import focal_bump

__all__ = ["MASK_NORMALISATIONS", "normalise_window_masks"]

MASK_NORMALISATIONS = ("max", "visible", "none")


def normalise_window_masks(
    mask: Tensor, mode: str, focal: bool, floor: float = 1e-4, pool: int = 3
) -> Tensor:
    """Normalise decoded window masks so that each window stays visible.

    Args:
        mask: decoded masks in [0, 1], (B, N, 1, h, w).
        mode: ``"max"`` (reference code), ``"visible"`` (maximum of the pooled,
            bump-weighted mask) or ``"none"``.
        focal: the windows are pasted with the focal bump (``"visible"`` weights by it).
        floor: lower bound of the divisor.
        pool: side of the averaging window of ``"visible"`` (odd; 1: no pooling).

    Returns:
        (B, N, 1, h, w): in [0, 1] for ``"max"`` and ``"none"``; for ``"visible"``
        non-negative, with the bump-weighted mask peaking at >= 1 (exactly 1 when
        ``pool`` is 1).
    """
    if mode == "none":
        return mask
    if mode == "max":
        return mask / mask.amax((-2, -1), keepdim=True).clamp_min(floor)
    if mode != "visible":
        raise ValueError(f"mask normalisation must be one of {MASK_NORMALISATIONS}, got {mode!r}")
    B, N, C, h, w = mask.shape
    visible = mask * focal_bump(h, w, dtype=mask.dtype, device=mask.device) if focal else mask
    if pool > 1:
        visible = F.avg_pool2d(
            visible.reshape(B * N, C, h, w), pool, stride=1, padding=pool // 2,
            count_include_pad=False,
        ).reshape(B, N, C, h, w)
    scale = visible.amax((-2, -1), keepdim=True).clamp_min(floor)
    return mask / scale
