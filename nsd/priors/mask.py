r"""The hull mask prior: each window's composited mask matches the pixels its hull individual owns.

The compositor's visible masks :math:`w_n(p)` learn from re-synthesis alone in NSD, and
stay blobby (raw-mask mIoU 0.2-0.3 at 128 x 128, docs/nsd.md). The visual hull of the
background residuals gives, without labels, an owner to every foreground pixel of every
view (:func:`nsd.cues.occupancy.owned_pixels`). With each window matched to a hull
individual (the proposal prior's matching, :func:`nsd.cues.proposals.match_proposals`),

.. math::
    L_\text{mask} = \frac{1}{|\Omega|} \sum_{p \in \Omega} \frac{1}{N}
        \sum_n \mathrm{BCE}\big(w_n(p), [o(p) = s_n]\big),

over the owned pixels :math:`\Omega` (:math:`o(p) \ge 0`), where :math:`s_n` is window
:math:`n`'s individual (windows matched to no valid individual target 0). Background
pixels are left to the ``foreground`` coverage term.
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["hull_mask_prior"]


def hull_mask_prior(weights: Tensor, owners: Tensor, matching: Tensor, valid: Tensor) -> Tensor:
    """:math:`L_\\text{mask}` (scalar).

    Args:
        weights: composited visible masks (B, N, H, W) in [0, 1].
        owners: each pixel's hull individual (B, H, W) int, -1 where none.
        matching: each window's individual (B, N) (index into the individuals).
        valid: (B, K) whether each individual is valid in that view.
    """
    owned = owners >= 0  # (B, H, W)
    ok = valid.gather(1, matching)  # (B, N)
    target = (owners[:, None] == matching[..., None, None]) & ok[..., None, None]
    p = weights.clamp(1e-4, 1 - 1e-4)
    bce = -(target * p.log() + (~target) * (1 - p).log())  # (B, N, H, W)
    return (bce.mean(1) * owned).sum() / owned.sum().clamp_min(1)  # 0 where nothing is owned
