r"""Colour models of the individuals: what a decomposition owns surely teaches it whom the rest is.

Where bodies touch, the mask ownership (:func:`nsd.inference.single.ownership`) rests on the
composited weights of blobby decoded masks, and the boundary between two bodies is where
their blobs meet, not where one body's pixels end. The image itself says more: two
individuals rarely have the same colours. Each window's colour histogram :math:`h_i` is
counted over the foreground pixels it owns *surely*, by at least ``margin`` nats of
ownership score over the runner-up, and pooled over the windows of one individual (in
multi-view inference the windows of one visual-hull individual in every view of the instant,
so that a camera that sees the bodies apart teaches the one where they overlap). Its
colour likelihood, with RGB quantised into ``bins`` levels per channel
(:math:`K = \mathrm{bins}^3` cells) and add-half smoothing,

.. math::
    p_i(c) = \frac{h_i(c) + \tfrac12}{\sum_{c'} h_i(c') + \tfrac{K}{2}},

is added to the log ownership score with ``weight``: :math:`\log o_i(p) + w \log p_i(I(p))`.
A window with few sure pixels has a near-uniform :math:`p_i` and leaves the learned ownership
as it was; where every window has the same colours the term is the same for all and changes
nothing. Which pixels are foreground is not changed, only who owns them.

Measured in docs/nsd.md ("Colour models of the individuals").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nsd.cues.colour_cells import colour_cells

__all__ = ["ColourModels", "colour_log_likelihood", "sure_owners"]


def sure_owners(score: Tensor, candidates: Tensor, margin: float) -> tuple[Tensor, Tensor]:
    """Each pixel's owner and whether it owns it surely.

    Args:
        score: log ownership scores (B, N, H, W).
        candidates: (B, H, W) bool, the pixels that may teach (e.g. claimed foreground).
        margin: nats by which the owner's score must beat every other window's.

    Returns:
        owner (B, H, W) long (argmax, first on ties) and sure (B, H, W) bool.
    """
    if score.shape[1] < 2:
        return torch.zeros_like(candidates, dtype=torch.long), candidates.clone()
    top = score.topk(2, dim=1)
    return top.indices[:, 0], candidates & (top.values[:, 0] - top.values[:, 1] > margin)


def colour_log_likelihood(
    images: Tensor,
    owner: Tensor,
    sure: Tensor,
    num_windows: int,
    bins: int,
    groups: Tensor | None = None,
) -> Tensor:
    r""":math:`\log p_i(I(p))` of every window at every pixel (module docstring).

    Args:
        images: (B, 3, H, W) in [0, 1].
        owner: (B, H, W) long in [0, N): the window that owns each pixel.
        sure: (B, H, W) bool: the pixels whose colours count towards their owner's histogram.
        num_windows: N.
        bins: levels per colour channel.
        groups: (B, N) long, windows with the same id >= 0 share one histogram (e.g. one
            individual in every view of an instant); -1 or None: a window alone.

    Returns:
        (B, N, H, W).
    """
    B, _, H, W = images.shape
    N, K = num_windows, bins**3
    cells = colour_cells(images, bins)
    window = torch.arange(B)[:, None, None] * N + owner  # (B, H, W) flat window index
    counts = torch.bincount((window * K + cells)[sure], minlength=B * N * K)
    counts = counts.reshape(B * N, K).to(images.dtype)
    if groups is not None:
        g = groups.reshape(-1)
        shared = int(g.max().clamp_min(-1)) + 1  # ids of the shared histograms
        ids = torch.where(g >= 0, g, shared + torch.arange(B * N))  # -1: a window alone
        pooled = counts.new_zeros(shared + B * N, K).index_add_(0, ids, counts)
        counts = pooled[ids]
    log_p = ((counts + 0.5) / (counts.sum(-1, keepdim=True) + 0.5 * K)).log()
    log_p = log_p.reshape(B, N, K)
    return log_p.gather(2, cells.reshape(B, 1, H * W).expand(B, N, H * W)).reshape(B, N, H, W)


@dataclass(frozen=True)
class ColourModels:
    """The colour models' settings (``inference.colour_model*``, conf/inference/default.yaml).

    Attributes:
        weight: of the colour log-likelihood in the ownership score (0: off).
        bins: levels per RGB channel of the histograms.
        margin: nats of ownership score by which a pixel's owner must lead to teach it.
    """

    weight: float
    bins: int
    margin: float

    def rescore(self, score: Tensor, images: Tensor, candidates: Tensor,
                groups: Tensor | None = None) -> Tensor:
        """Log ownership scores (B, N, H, W) with the colour term added.

        Args:
            score: log ownership scores (B, N, H, W).
            images: (B, 3, H, W) in [0, 1].
            candidates: (B, H, W) bool, the foreground pixels a window claims.
            groups: as :func:`colour_log_likelihood`.
        """
        if self.weight <= 0 or score.shape[1] < 2:
            return score
        owner, sure = sure_owners(score, candidates, self.margin)
        ll = colour_log_likelihood(images, owner, sure, score.shape[1], self.bins, groups)
        return score + self.weight * ll
