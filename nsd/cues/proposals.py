r"""Label-free window proposals from the background residual, and their matching to windows.

The median background makes the foreground visible for free:
:math:`e = \mathrm{evidence}(|I - B|)` (:mod:`nsd.cues.evidence`). Clustering the
foreground pixels of a frame into ``k`` groups (weighted k-means on pixel
coordinates, the vertical axis shrunk by ``y_weight`` because bodies are
taller than wide) gives one blob per subject when subjects stand apart, and a
left/right split of a merged blob when they overlap. Each blob gives a
proposal window centred on its weighted mean with half-size
:math:`2\sigma / \mathrm{fill}` per axis (:math:`2\sigma` covers a uniform
blob; ``fill`` = 0.75 keeps the subject inside the focal bump's bright core).

The priors that use the proposals: :mod:`nsd.priors.proposal`.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor

__all__ = ["evidence_proposals", "match_proposals"]

OFF_WINDOW_COST = 1e3  # added to a window that is off: above any cost between bounded boxes


def evidence_proposals(
    evidence: Tensor,
    k: int,
    iterations: int = 10,
    y_weight: float = 0.35,
    fill: float = 0.75,
    min_mass: float = 8.0,
    min_scale: float = 0.2,
    max_scale: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """Proposal windows from foreground evidence by weighted k-means.

    Args:
        evidence: (B, H, W) in [0, 1].
        k: number of proposals (windows).
        iterations: Lloyd iterations.
        y_weight: scale of the vertical axis in the clustering distance.
        fill: fraction of the window half-size the blob should fill.
        min_mass: blobs with less evidence (pixels) are invalid.
        min_scale, max_scale: bounds of the proposal scales (as the detector's).

    Returns:
        boxes (B, k, 4) = (sx, sy, tx, ty) normalised; valid (B, k) bool.
    """
    B, H, W = evidence.shape
    ys = (2 * torch.arange(H, dtype=evidence.dtype) + 1) / H - 1
    xs = (2 * torch.arange(W, dtype=evidence.dtype) + 1) / W - 1
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pts = torch.stack([gx.flatten(), gy.flatten()], -1)  # (P, 2)
    w = evidence.flatten(1)  # (B, P)
    mass = w.sum(1).clamp_min(1e-6)
    # initial centres at the k x-quantiles of the evidence, at its mean height
    order = torch.argsort(pts[:, 0])
    cdf = torch.cumsum(w[:, order], 1) / mass[:, None]
    q = (torch.arange(k, dtype=evidence.dtype) + 0.5) / k
    idx = torch.searchsorted(cdf.contiguous(), q.expand(B, k).contiguous()).clamp_max(
        len(order) - 1
    )
    cx = pts[order[idx], 0]
    cy = ((w * pts[:, 1]).sum(1) / mass)[:, None].expand(B, k)
    centres = torch.stack([cx, cy], -1)  # (B, k, 2)
    scale = torch.tensor([1.0, y_weight], dtype=evidence.dtype)
    for _ in range(iterations):
        d = ((pts[None, None] - centres[:, :, None]) * scale).pow(2).sum(-1)  # (B, k, P)
        assign = torch.nn.functional.one_hot(d.argmin(1), k).permute(0, 2, 1).to(w.dtype)
        cw = assign * w[:, None]  # (B, k, P)
        m = cw.sum(-1, keepdim=True)
        new = (cw @ pts) / m.clamp_min(1e-6)
        centres = torch.where(m > 0, new, centres)
    d = ((pts[None, None] - centres[:, :, None]) * scale).pow(2).sum(-1)
    cw = torch.nn.functional.one_hot(d.argmin(1), k).permute(0, 2, 1).to(w.dtype) * w[:, None]
    m = cw.sum(-1)
    var = (cw[..., None] * (pts[None, None] - centres[:, :, None]).pow(2)).sum(2) / m[
        ..., None
    ].clamp_min(1e-6)
    half = 2 * var.sqrt() / fill
    boxes = torch.cat([half.clamp(min_scale, max_scale), centres], -1)
    return boxes, m >= min_mass


def _cost(a: Tensor, b: Tensor) -> Tensor:
    """(B, N, M) squared distance of centres plus squared log-scale difference."""
    dt = (a[:, :, None, 2:] - b[:, None, :, 2:]).pow(2).sum(-1)
    ds = (a[:, :, None, :2].log() - b[:, None, :, :2].log()).pow(2).sum(-1)
    return dt + ds


@torch.no_grad()
def match_proposals(
    boxes: Tensor, proposals: Tensor, valid: Tensor, active: Tensor | None = None
) -> Tensor:
    """Exact min-cost matching of windows to proposals (permutations; N is small).

    Args:
        boxes: (B, N, 4); proposals: (B, N, 4); valid: (B, N) bool.
        active: (B, N) bool, windows that are on (None: all). A valid proposal goes
            to a window that is off only when no active window is left for it.

    Returns:
        (B, N) long: the proposal of each window.
    """
    N = boxes.shape[1]
    c = _cost(boxes, proposals)
    if active is not None:
        c = c + OFF_WINDOW_COST * (~active)[:, :, None].to(c.dtype)
    c = c * valid[:, None, :]
    perms = torch.tensor(list(itertools.permutations(range(N))), device=c.device)  # (N!, N)
    total = c[:, torch.arange(N, device=c.device)[None], perms].sum(-1)  # (B, N!)
    return perms[total.argmin(1)]


