r"""Neighbours of one colour share an owner: a contrast-sensitive Potts term on the mask ownership.

Where two bodies touch, each pixel's owner is the largest of its log ownership scores
(:func:`nsd.inference.single.ownership`, with the hull's bonus and the individuals' colour
models), decided pixel by pixel. Where the scores are close, the boundary between two bodies
wanders: a decoded window mask reaches over its neighbour, or a body is sprinkled with its
neighbour's pixels. Neighbouring pixels of one colour most likely belong to one body, and a
boundary between two bodies most likely lies on a colour edge. A conditional random field
says so with a pairwise energy on the 8 neighbours :math:`q` of each pixel :math:`p`,

.. math::
    E_{pq}(i, j) = w\, \mu_{ij}\, k(p, q), \qquad
    k(p, q) = \exp\!\left(-\frac{\lVert I(p) - I(q) \rVert^2}{2 \sigma^2}\right),

paid when :math:`p` goes to window :math:`i` and :math:`q` to window :math:`j`, only between
claimed foreground pixels (the floor is nobody's and costs nothing). :math:`\mu_{ij}` is the
labels' compatibility: 0 on the diagonal, and for two windows the colour models tell apart
their :math:`\kappa_{ij}` clipped to [0, 1]
(:func:`nsd.inference.colour_models.window_compatibility`; 1 where it was not measured).
Individuals of one colour (:math:`\kappa \approx 0`) pay nothing: an edge-free junction
between look-alikes says nothing about where one ends, and smoothing there only shortens the
boundary at the smaller one's expense.

The field is solved approximately by ``steps`` rounds of mean-field (Krähenbühl and Koltun
2011, on a local grid): with :math:`Q_j(q)` the softmax of the current scores,

.. math::
    s_i(p) \leftarrow \log o_i(p) - w \sum_j \mu_{ij} \sum_{q \in N_8(p)} k(p, q)\, Q_j(q),

and the owner is the argmax of the last scores. Which pixels are foreground does not change,
only who owns them. Measured in docs/nsd.md ("Neighbours of one colour").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["NEIGHBOURS_OFF", "NEIGHBOUR_SIGMA", "NEIGHBOUR_STEPS", "NEIGHBOUR_WEIGHT",
           "NeighbourAgreement", "colour_affinities", "neighbour_agreement"]

# The shipped defaults when no config gives them; conf/inference/default.yaml
# (``inference.neighbour_weight``, ``inference.neighbour_sigma``) holds the same values, chosen
# on four checkpoints (docs/benchmarks/neighbours.md). Mean-field rounds: 3 and 6 scored alike.
NEIGHBOUR_WEIGHT = 1.0
NEIGHBOUR_SIGMA = 0.2
NEIGHBOUR_STEPS = 3


def _neighbours(x: Tensor) -> list[Tensor]:
    """The 9 views of ``x`` (..., H, W) shifted to each pixel's 3 x 3 neighbourhood, zero
    outside the frame: entry ``(dy + 1) * 3 + (dx + 1)`` holds ``x[..., y + dy, x + dx]``."""
    H, W = x.shape[-2:]
    padded = F.pad(x, (1, 1, 1, 1))
    return [padded[..., dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)]


def colour_affinities(images: Tensor, claim: Tensor, sigma: float) -> Tensor:
    r""":math:`k(p, q)` of each pixel with its 8 neighbours, 0 unless both are claimed.

    Args:
        images: (B, 3, H, W) in [0, 1].
        claim: (B, H, W) bool, the claimed foreground.
        sigma: colour scale :math:`\sigma` (RGB distance in [0, 1] units).

    Returns:
        (B, 9, H, W): neighbour ``(dy + 1) * 3 + (dx + 1)`` of each pixel; the centre (4) is 0.
    """
    near = torch.stack(_neighbours(images), 2)  # (B, 3, 9, H, W)
    near_claim = torch.stack(_neighbours(claim.to(images.dtype)), 1)  # (B, 9, H, W)
    k = torch.exp(-(near - images[:, :, None]).pow(2).sum(1) / (2 * sigma**2))
    k = k * near_claim * claim[:, None]
    k[:, 4] = 0
    return k


def neighbour_agreement(score: Tensor, images: Tensor, claim: Tensor, weight: float,
                        sigma: float, steps: int = NEIGHBOUR_STEPS,
                        compatibility: Tensor | None = None) -> Tensor:
    """Log ownership scores after ``steps`` mean-field rounds of the Potts term (module docstring).

    Args:
        score: log ownership scores (B, N, H, W).
        images: (B, 3, H, W) in [0, 1].
        claim: (B, H, W) bool, the foreground pixels some window claims.
        weight: :math:`w` (0: ``score`` unchanged).
        sigma: colour scale of :func:`colour_affinities`.
        steps: mean-field rounds.
        compatibility: :math:`\\mu` (B, N, N), 0 on the diagonal; None: Potts (1 off it).

    Returns:
        (B, N, H, W); equal to ``score`` where ``weight`` <= 0, ``steps`` is 0 or N < 2.
    """
    B, N = score.shape[:2]
    if weight <= 0 or steps <= 0 or N < 2:
        return score
    if compatibility is None:
        compatibility = (1 - torch.eye(N, dtype=score.dtype)).expand(B, N, N)
    k = colour_affinities(images.to(score.dtype), claim, sigma)  # (B, 9, H, W)
    mu = compatibility.to(score.dtype)
    out = score
    for _ in range(steps):
        near_q = _neighbours(torch.softmax(out, 1))
        message = torch.zeros_like(score)  # (B, N, H, W): neighbours' agreement with each j
        for n, q in enumerate(near_q):
            if n != 4:
                message.addcmul_(q, k[:, n:n + 1])
        out = score - weight * torch.einsum("bij,bjhw->bihw", mu, message)
    return out


@dataclass(frozen=True)
class NeighbourAgreement:
    """The Potts term's settings (``inference.neighbour_*``, conf/inference/default.yaml).

    Attributes:
        weight: :math:`w` (0: off).
        sigma: colour scale :math:`\\sigma`.
        steps: mean-field rounds.
    """

    weight: float = NEIGHBOUR_WEIGHT
    sigma: float = NEIGHBOUR_SIGMA
    steps: int = NEIGHBOUR_STEPS

    def rescore(self, score: Tensor, images: Tensor, claim: Tensor,
                compatibility: Tensor | None = None) -> Tensor:
        """:func:`neighbour_agreement` with these settings."""
        return neighbour_agreement(score, images, claim, self.weight, self.sigma, self.steps,
                                   compatibility)


NEIGHBOURS_OFF = NeighbourAgreement(0.0)
