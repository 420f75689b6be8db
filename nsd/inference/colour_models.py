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
A window with few sure pixels has a near-uniform :math:`p_i`, which likes every common colour
less than a neighbour's peaked histogram does, so it tends to lose contested pixels to its
neighbours (a whole look-alike's mask, at worst). Shrinking the histograms towards the frame's
colours instead was measured and not kept: it lost more identities over time than it found
instances (docs/nsd.md, "A window with few sure pixels"). Which pixels are foreground is not
changed, only who owns them.

Individuals of one colour (mice of one strain) are the exception: their histograms differ
only by the pixels each happened to own surely, and that noise moved pixels between them
(mask mIoU 0.009-0.017 lower than without the models on six runs of one texture). So
individuals that colour cannot tell apart share one model (``separation``,
:func:`colour_classes`): for two individuals seen in one frame, each surely owned pixel of
either is set against the other's histogram, its own counted without the pixel; where the
share :math:`a_{ij}` that goes back to its owner gives :math:`\kappa_{ij} = 2 a_{ij} - 1`
below ``separation`` (one colour for both: about 0 or below; distinct coats: near 1), the
two are joined. Joined individuals, pooled, look the same to the colour term, which then
tells them only from the others.

Measured in docs/nsd.md ("Colour models of the individuals"; "Speckled masks, and colours
that do not tell individuals apart").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nsd.cues.colour_cells import colour_cells

# Pixels two individuals must own surely between them before their colours are compared.
MIN_PAIR_PIXELS = 20

__all__ = [
    "ColourModels",
    "colour_classes",
    "colour_log_likelihood",
    "colour_pair_separation",
    "sure_owners",
    "window_compatibility",
]


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
            groups: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each window's own histogram (B * N, K), the individual each window belongs to (B * N,)
    (its group id, or an id of its own), the pixels' colour cells (B, H, W) and their
    owners' flat window indices (B, H, W)."""
    B = images.shape[0]
    N, K = num_windows, bins**3
    cells = colour_cells(images, bins)
    window = torch.arange(B)[:, None, None] * N + owner  # (B, H, W) flat window index
    counts = torch.bincount((window * K + cells)[sure], minlength=B * N * K)
    counts = counts.reshape(B * N, K).to(images.dtype)
    g = groups.reshape(-1) if groups is not None else torch.full((B * N,), -1)
    shared = int(g.max().clamp_min(-1)) + 1  # ids of the shared histograms
    ids = torch.where(g >= 0, g, shared + torch.arange(B * N))  # -1: a window alone
    return counts, ids, cells, window


def _pooled(counts: Tensor, ids: Tensor) -> Tensor:
    """The histograms (B * N, K) of the windows' individuals: ``counts`` summed over the
    windows of one id."""
    pooled = counts.new_zeros(int(ids.max()) + 1 if len(ids) else 0, counts.shape[1])
    return pooled.index_add_(0, ids, counts)[ids]


def _models(images: Tensor, owner: Tensor, sure: Tensor, num_windows: int, bins: int,
            groups: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`_counts` and the individuals' pooled histograms (B * N, K) with their
    log-likelihoods (B, N, H, W): ``counts, ids, cells, window, pooled, ll``."""
    counts, ids, cells, window = _counts(images, owner, sure, num_windows, bins, groups)
    pooled = _pooled(counts, ids)
    return counts, ids, cells, window, pooled, _log_likelihood(pooled, cells)


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
    return _models(images, owner, sure, num_windows, bins, groups)[-1]


def colour_pair_separation(images: Tensor, owner: Tensor, sure: Tensor, num_windows: int,
                           bins: int, groups: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""How well colour tells each two individuals apart: :math:`\kappa_{ij}` and the pixels
    it is measured on, both (I, I) over the individuals' ids (module docstring).

    For two individuals :math:`i, j` seen in one frame, each surely owned pixel of either is
    set against the other's histogram, its own counted without it (leave-one-out);
    :math:`a_{ij}` is the share that goes back to its owner and
    :math:`\kappa_{ij} = 2 a_{ij} - 1`. An individual's id is its group (``groups``) or,
    for a window alone, ``max(groups) + 1`` + its flat window index ``b * N + n``.

    Args:
        images, owner, sure, num_windows, bins, groups: as :func:`colour_log_likelihood`.
    """
    _, ids, cells, window, pooled, ll = _models(images, owner, sure, num_windows, bins, groups)
    return _pair_kappa(pooled, ll, ids, cells, window, owner, sure)


def colour_classes(images: Tensor, owner: Tensor, sure: Tensor, num_windows: int, bins: int,
                   separation: float, groups: Tensor | None = None) -> Tensor:
    r"""The individuals that colour cannot tell apart, joined: a class id per window (B * N,).

    Two individuals are joined where :func:`colour_pair_separation`'s :math:`\kappa_{ij}` is
    below ``separation``, measured on at least ``MIN_PAIR_PIXELS`` pixels; classes are the
    joined individuals' connected sets, each named by its smallest id.

    Args:
        images, owner, sure, num_windows, bins, groups: as :func:`colour_log_likelihood`.
        separation: the :math:`\kappa_{ij}` below which two individuals are joined.
    """
    _, ids, cells, window, pooled, ll = _models(images, owner, sure, num_windows, bins, groups)
    return _classes(*_pair_kappa(pooled, ll, ids, cells, window, owner, sure), ids, separation)


def _pair_kappa(pooled: Tensor, ll: Tensor, ids: Tensor, cells: Tensor, window: Tensor,
                owner: Tensor, sure: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`colour_pair_separation` from the individuals' histograms (B * N, K) and their
    likelihoods (B, N, H, W)."""
    B, N, K = ll.shape[0], ll.shape[1], pooled.shape[1]
    size = int(ids.max()) + 1 if len(ids) else 0
    w, c = window[sure], cells[sure]
    own = ((pooled[w, c] - 0.5) / (pooled.sum(-1)[w] - 1 + 0.5 * K)).log()  # leave-one-out
    frame = torch.arange(B)[:, None, None].expand_as(owner)[sure]
    rival = frame[:, None] * N + torch.arange(N)  # (P, N) flat windows of the pixel's frame
    mine, theirs = ids[w][:, None].expand_as(rival), ids[rival]
    lost = ll.permute(0, 2, 3, 1)[sure] >= own[:, None]  # (P, N)
    other = mine != theirs
    pair = (mine * size + theirs)[other]
    lost_n = torch.bincount(pair, weights=lost[other].to(ll.dtype), minlength=size * size)
    seen_n = torch.bincount(pair, minlength=size * size).to(ll.dtype)
    lost_n, seen_n = lost_n.reshape(size, size), seen_n.reshape(size, size)
    lost_n, seen_n = lost_n + lost_n.T, seen_n + seen_n.T
    return 1 - 2 * lost_n / seen_n.clamp_min(1), seen_n


def window_compatibility(kappa: Tensor, seen: Tensor, ids: Tensor, num_windows: int) -> Tensor:
    r"""How much colour tells each two windows of a frame apart, (B, N, N) in [0, 1]: their
    individuals' :math:`\kappa_{ij}` (:func:`colour_pair_separation`) clipped to [0, 1]; 1 where
    it was measured on fewer than ``MIN_PAIR_PIXELS`` pixels; 0 for two windows of one
    individual and on the diagonal. The compatibility of
    :mod:`nsd.inference.neighbours`' Potts term.

    Args:
        kappa, seen: (I, I) over the individuals' ids; ids: (B * N,) each window's individual.
        num_windows: N.
    """
    ids = ids.reshape(-1, num_windows)
    measured = seen >= MIN_PAIR_PIXELS
    known = torch.where(measured, kappa.clamp(0, 1), torch.ones_like(kappa))
    out = known[ids[:, :, None], ids[:, None, :]]
    return out * (ids[:, :, None] != ids[:, None, :])


def _classes(kappa: Tensor, seen: Tensor, ids: Tensor, separation: float) -> Tensor:
    """:func:`colour_classes` from :func:`_pair_kappa`'s (I, I) ``kappa`` and ``seen`` and the
    windows' individuals ``ids`` (B * N,)."""
    join = (seen >= MIN_PAIR_PIXELS) & (kappa < separation)
    size = len(kappa)
    cls = torch.arange(size)
    while True:  # each individual takes the smallest class id among those it joins
        nxt = torch.where(join, cls[None, :], size).amin(1).minimum(cls)
        if torch.equal(nxt, cls):
            return cls[ids]
        cls = nxt


@dataclass(frozen=True)
class ColourModels:
    """The colour models' settings (``inference.colour_model*``, conf/inference/default.yaml).

    Attributes:
        weight: of the colour log-likelihood in the ownership score (0: off).
        bins: levels per RGB channel of the histograms.
        margin: nats of ownership score by which a pixel's owner must lead to teach it.
        separation: individuals whose colours tell them apart by less than this
            (:func:`colour_classes`) share one colour model (0: each its own).
    """

    weight: float
    bins: int
    margin: float
    separation: float = 0.0

    def rescore(self, score: Tensor, images: Tensor, candidates: Tensor,
                groups: Tensor | None = None) -> Tensor:
        """Log ownership scores (B, N, H, W) with the colour term added (one model for the
        individuals it cannot tell apart, ``separation``).

        Args:
            score: log ownership scores (B, N, H, W).
            images: (B, 3, H, W) in [0, 1].
            candidates: (B, H, W) bool, the foreground pixels a window claims.
            groups: as :func:`colour_log_likelihood`.
        """
        return self.rescore_with_compatibility(score, images, candidates, groups)[0]

    def rescore_with_compatibility(self, score: Tensor, images: Tensor, candidates: Tensor,
                                   groups: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """:meth:`rescore`'s scores and the windows' :func:`window_compatibility` (B, N, N)
        from the same histograms (None where the colour term is off or N < 2)."""
        if self.weight <= 0 or score.shape[1] < 2:
            return score, None
        owner, sure = sure_owners(score, candidates, self.margin)
        counts, ids, cells, window, pooled, ll = _models(images, owner, sure, score.shape[1],
                                                         self.bins, groups)
        kappa, seen = _pair_kappa(pooled, ll, ids, cells, window, owner, sure)
        if self.separation > 0:  # one model for the individuals colour cannot tell apart
            classes = _classes(kappa, seen, ids, self.separation)
            if not torch.equal(classes, ids):  # some were joined
                ll = _log_likelihood(_pooled(counts, classes), cells)
        compatibility = window_compatibility(kappa, seen, ids, score.shape[1])
        return score + self.weight * ll, compatibility
