r"""Appearance-based association of windows across views (NSD eq. 4-5).

Windows are detected independently in views ``v`` and ``w``. Their appearance
vectors are compared by cosine similarity on the first ``dims`` (16 of 128)
entries, leaving the rest free to encode what all subjects share:

.. math::
    M_{j,i} = \frac{a_{v,j} \cdot a_{w,i}}{\|a_{v,j}\|\,\|a_{w,i}\| + \epsilon},
    \qquad A = \operatorname{softmax}_i(\beta M), \ \beta = 10,

and the windows decoded from view ``w`` are re-ordered into the slots of view
``v`` as :math:`\bar I_{v,j} \leftarrow \sum_i A_{j,i} \bar I_{w,i}`. At inference
the softmax is replaced by the one-hot argmax. Zero appearance vectors give
:math:`M = 0` (uniform rows) with zero, finite gradients; vectors of any
magnitude are compared without overflow (each is divided by its largest entry
first, which leaves :math:`M` unchanged); the softmax is computed stably for any
``beta``.

With an upper bound of windows (learned presence), a source window that is switched
off (presence below 0.5 under the hard gate, or not encoded at inference) must not
supply any target slot: its score is lowered by a constant :math:`c` far beyond any
score's range,

.. math::
    M'_{j,i} = M_{j,i} - c\,[\,i \text{ off}\,], \qquad c = 10^4,

so that it gets zero weight whenever a source window is on; a frame whose source
windows are all off keeps its association unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "appearance_similarity",
    "apply_association",
    "association_softmax",
    "exclude_absent",
    "hard_association",
]

ABSENT_PENALTY = 1e4  # c above: beyond any cosine similarity plus geometry cost


def appearance_similarity(
    app_target: Tensor, app_source: Tensor, dims: int = 16, eps: float = 1e-4
) -> Tensor:
    """Cosine similarity matrix :math:`M` on the first ``dims`` appearance entries.

    Args:
        app_target: appearance of the target view's windows, (B, N, D).
        app_source: appearance of the source view's windows, (B, M, D).
        dims: leading entries compared (NSD: 16).
        eps: added to the norms' product.

    Returns:
        (B, N, M); ``M[b, j, i]`` compares target window j with source window i.
    """
    a = app_target[..., :dims]
    b = app_source[..., :dims]
    # M is unchanged by dividing a and b by any constants s_a, s_b (eps / (s_a s_b) in
    # the denominator); s = max(1, max |entry|) keeps the dot products and norms of
    # large vectors from overflowing (float32 at |a| ~ 1e19) and is exactly 1 otherwise
    s_a = a.detach().abs().amax(-1, keepdim=True).clamp_min(1.0)
    s_b = b.detach().abs().amax(-1, keepdim=True).clamp_min(1.0)
    a, b = a / s_a, b / s_b
    dot = torch.einsum("bjd,bid->bji", a, b)
    norms = a.norm(dim=-1).unsqueeze(-1) * b.norm(dim=-1).unsqueeze(-2)
    return dot / (norms + eps / (s_a * s_b.transpose(-1, -2)))


def exclude_absent(score: Tensor, present: Tensor | None) -> Tensor:
    """Lower the scores of switched-off source windows by ``ABSENT_PENALTY``.

    Args:
        score: association scores (B, N, M) (target window j, source window i).
        present: (B, M) bool, the source windows that are on; None keeps ``score``.

    Returns:
        (B, N, M), with the same gradient as ``score``.
    """
    if present is None:
        return score
    absent = ~present & present.any(-1, keepdim=True)  # rows with no source on: unchanged
    return score - ABSENT_PENALTY * absent[:, None, :].to(score.dtype)


def association_softmax(similarity: Tensor, beta: float = 10.0) -> Tensor:
    """Soft association :math:`A = \\mathrm{softmax}(\\beta M)` over source windows, (B, N, M)."""
    return F.softmax(beta * similarity, dim=-1)


def hard_association(similarity: Tensor) -> Tensor:
    """One-hot argmax association used at inference, (B, N, M)."""
    return F.one_hot(similarity.argmax(-1), similarity.shape[-1]).to(similarity.dtype)


def apply_association(association: Tensor, source: Tensor) -> Tensor:
    """Re-order source-view tensors into target slots: ``out_j = sum_i A_ji source_i``.

    Args:
        association: (B, N, M).
        source: (B, M, ...) any per-window tensor (decoded windows, masks).

    Returns:
        (B, N, ...).
    """
    B, M = source.shape[:2]
    flat = source.reshape(B, M, -1)
    return torch.bmm(association.to(flat.dtype), flat).reshape(B, -1, *source.shape[2:])
