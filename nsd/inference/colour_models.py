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
as it was. Which pixels are foreground is not changed, only who owns them.

Individuals of one colour (mice of one strain) are the exception: their histograms differ
only by the pixels each happened to own surely, and that noise moved pixels between them
(mask mIoU 0.009-0.017 lower than without the models on six runs of one texture). So the
term is used in an instant only where the models tell its individuals apart
(``separation``, :func:`colour_separation`): each surely owned pixel is given to the window
whose histogram, its own counted without the pixel, likes its colour best, and
:math:`\kappa` is the share given back to the owner, above the chance :math:`1/n` of the
instant's :math:`n` individuals, :math:`\kappa = (a - 1/n) / (1 - 1/n)`. One colour per
individual gives :math:`\kappa` near 1, one colour for all near 0 or below.

Measured in docs/nsd.md ("Colour models of the individuals").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nsd.cues.colour_cells import colour_cells

__all__ = ["ColourModels", "colour_log_likelihood", "colour_separation", "sure_owners"]


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


def _counts(images: Tensor, owner: Tensor, sure: Tensor, num_windows: int, bins: int,
            groups: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Each window's (pooled) histogram (B * N, K), the pixels' colour cells (B, H, W) and
    their owners' flat window indices (B, H, W)."""
    B = images.shape[0]
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
    return counts, cells, window


def _log_likelihood(counts: Tensor, cells: Tensor) -> Tensor:
    r""":math:`\log p_i(I(p))` (B, N, H, W) from the histograms (B * N, K), cells (B, H, W)."""
    B, H, W = cells.shape
    K = counts.shape[1]
    log_p = ((counts + 0.5) / (counts.sum(-1, keepdim=True) + 0.5 * K)).log()
    log_p = log_p.reshape(B, -1, K)
    N = log_p.shape[1]
    return log_p.gather(2, cells.reshape(B, 1, H * W).expand(B, N, H * W)).reshape(B, N, H, W)


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
    counts, cells, _ = _counts(images, owner, sure, num_windows, bins, groups)
    return _log_likelihood(counts, cells)


def colour_separation(
    images: Tensor,
    owner: Tensor,
    sure: Tensor,
    num_windows: int,
    bins: int,
    groups: Tensor | None = None,
    instants: Tensor | None = None,
) -> Tensor:
    r"""How well the colour models tell an instant's individuals apart: :math:`\kappa` per
    frame (B,), the same for every frame of one instant (module docstring).

    Every surely owned pixel is given to the window whose histogram likes its colour best,
    its own window's histogram counted without it (leave-one-out); :math:`a` is the share
    of the instant's sure pixels that go back to their owner and :math:`n` the number of
    windows that own some, and :math:`\kappa = (a - 1/n) / (1 - 1/n)`: 1 where colours
    alone say who is who, about 0 (or below) where the individuals look alike.

    Args:
        images, owner, sure, num_windows, bins, groups: as :func:`colour_log_likelihood`.
        instants: (B,) long, the frames of one instant (the views of one time step) share
            an id; None: each frame alone.
    """
    counts, cells, window = _counts(images, owner, sure, num_windows, bins, groups)
    return _kappa(counts, cells, window, _log_likelihood(counts, cells), owner, sure, groups,
                  instants)


def _kappa(counts: Tensor, cells: Tensor, window: Tensor, ll: Tensor, owner: Tensor,
           sure: Tensor, groups: Tensor | None, instants: Tensor | None) -> Tensor:
    """:func:`colour_separation` from :func:`_counts` and :func:`_log_likelihood`."""
    B, N = ll.shape[:2]
    K = counts.shape[1]
    dtype = ll.dtype
    instants = torch.arange(B) if instants is None else instants
    frame = torch.arange(B)[:, None, None].expand_as(owner)[sure]
    w, c = window[sure], cells[sure]
    own = ((counts[w, c] - 0.5) / (counts.sum(-1)[w] - 1 + 0.5 * K)).log()  # leave-one-out
    rivals = ll.permute(0, 2, 3, 1)[sure]  # (P, N)
    rivals[torch.arange(len(w)), owner[sure]] = -torch.inf
    back = (own > rivals.max(1).values).to(dtype)
    moment = instants[frame]
    count = int(instants.max()) + 1 if len(instants) else 0
    right = torch.zeros(count, dtype=dtype).index_add_(0, moment, back)
    pixels = torch.zeros(count, dtype=dtype).index_add_(0, moment, torch.ones_like(back))
    ident = groups.reshape(-1) if groups is not None else torch.arange(B * N)
    ident = torch.where(ident >= 0, ident, B * N + torch.arange(B * N))  # a window alone
    owns = torch.zeros(count, int(ident.max()) + 1 if len(ident) else 0, dtype=torch.bool)
    owns[moment, ident[w]] = True
    n = owns.sum(1).clamp_min(2).to(dtype)
    kappa = (right / pixels.clamp_min(1) - 1 / n) / (1 - 1 / n)
    return torch.where(pixels > 0, kappa, torch.zeros(count, dtype=dtype))[instants]


@dataclass(frozen=True)
class ColourModels:
    """The colour models' settings (``inference.colour_model*``, conf/inference/default.yaml).

    Attributes:
        weight: of the colour log-likelihood in the ownership score (0: off).
        bins: levels per RGB channel of the histograms.
        margin: nats of ownership score by which a pixel's owner must lead to teach it.
        separation: the colour term is used in an instant only where its
            :func:`colour_separation` reaches this (0: everywhere).
    """

    weight: float
    bins: int
    margin: float
    separation: float = 0.0

    def rescore(self, score: Tensor, images: Tensor, candidates: Tensor,
                groups: Tensor | None = None, instants: Tensor | None = None) -> Tensor:
        """Log ownership scores (B, N, H, W) with the colour term added (in the instants
        whose individuals it tells apart, ``separation``).

        Args:
            score: log ownership scores (B, N, H, W).
            images: (B, 3, H, W) in [0, 1].
            candidates: (B, H, W) bool, the foreground pixels a window claims.
            groups: as :func:`colour_log_likelihood`; instants: as :func:`colour_separation`.
        """
        if self.weight <= 0 or score.shape[1] < 2:
            return score
        owner, sure = sure_owners(score, candidates, self.margin)
        counts, cells, window = _counts(images, owner, sure, score.shape[1], self.bins, groups)
        ll = _log_likelihood(counts, cells)
        if self.separation > 0:
            kappa = _kappa(counts, cells, window, ll, owner, sure, groups, instants)
            ll = ll * (kappa >= self.separation).to(ll.dtype)[:, None, None, None]
        return score + self.weight * ll
