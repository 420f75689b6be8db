r"""Label-free window presence: a window is present if it explains foreground no other does.

With an upper bound of :math:`N` windows, the detector predicts a presence
:math:`p_i \in [0, 1]` per window. Gating the image loss by :math:`p_i` and
pushing it down with a sparsity prior collapses every presence to 0: a blurry
early window reconstructs worse than the median background it covers, so the
image loss itself lowers :math:`p_i`, and a low presence shrinks the gradients
that would teach the window (docs/benchmarks/count.md). Here no image gradient
reaches the presence: the image loss composites the windows that are on with a
detached 0/1 gate (``model.presence_gate=hard``; ``none`` keeps every window, as
with a fixed :math:`N`) and the presence learns from a detached target, the
window's *marginal contribution* to explaining the foreground. The hard gate
makes the windows that stay on explain each individual whole, while the
windows that are off keep being evaluated (their ungated masks), so they turn
on again where foreground is left unexplained.

With the soft foreground evidence :math:`e(x) \in [0, 1]` (background residual,
:func:`nsd.cues.evidence.foreground_evidence`), the ungated pasted masks
:math:`m_i(x) \in [0, 1]` and the window areas :math:`A_i` (``normalise=mask``:
the mask's own area :math:`\max(\sum_x m_i, a_{min})`, so that :math:`g_i` below is
the fraction of the mask that lands on unexplained foreground; ``box``:
:math:`s_{x,i} s_{y,i} H W` pixels), windows are accepted greedily:
starting from nothing explained, :math:`c_0(x) = 0`, the windows are evaluated
in order of their current (detached) presence, most present first, each by its
area-normalised gain given the windows accepted before it,

.. math::
    g_i = \frac{1}{A_i} \sum_x m_i(x)\, e(x)\, \big(1 - c(x)\big),

its target is :math:`y_i = [g_i \ge \delta]` (``margin``) and, if accepted, what
it explains is added, :math:`c \leftarrow c + (1 - c)\, m_i`. Hence an empty
window (:math:`e = 0` under its mask) is off; of two duplicates of the same
individual exactly one is on, the more present (the second gains nothing once
the first explains the individual); and a window on each of several
individuals is on. Ordering by presence makes the target self-consistent: the
window that is on stays on while it explains its individual. Ordered by gain
instead, the accepted one of several near-duplicates changed from step to step,
every window's presence regressed to the mean of its 0/1 targets (below 0.5),
and all were off (measured: 0.05 active windows per view for one individual).
With a cap (``max_on``; ``prior_presence.cap=proposals``: the number of
individuals the label-free visual hull finds in the frame and view,
:mod:`nsd.cues.occupancy`), no more windows than the cap are accepted, so windows
on parts of one individual cannot all stay on.
:math:`y` carries no gradient; the presence learns it by
binary cross-entropy, :math:`L = \frac{1}{BN}\sum_{b,i} \mathrm{BCE}(p_{b,i}, y_{b,i})`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import median_filter
from torch import Tensor

__all__ = [
    "marginal_presence_target",
    "presence_target_loss",
    "ranked_presence_target",
    "window_area",
]


def window_area(boxes: Tensor, image_size: tuple[int, int]) -> Tensor:
    """Area in pixels of windows (B, N, 4) = (sx, sy, tx, ty): :math:`s_x s_y H W`, shape (B, N)."""
    H, W = image_size
    return boxes[..., 0] * boxes[..., 1] * (H * W)


@torch.no_grad()
def marginal_presence_target(
    masks: Tensor,
    evidence: Tensor,
    area: Tensor,
    margin: float = 0.1,
    order: Tensor | None = None,
    max_on: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Greedy marginal-gain presence targets (detached).

    Args:
        masks: ungated pasted window masks (B, N, H, W) in [0, 1].
        evidence: foreground evidence (B, H, W) in [0, 1].
        area: window areas (B, N) in pixels (:func:`window_area`).
        margin: smallest newly explained foreground, as a fraction of the window's area.
        order: (B, N) the windows' current presences: evaluated most present first
            (None: by the largest gain).
        max_on: (B,) at most this many windows are on (e.g. the individuals the
            multi-view visual hull finds in the frame); None: no cap.

    Returns:
        target (B, N) in {0, 1} and gain (B, N), each window's area-normalised gain
        given the windows accepted before it was evaluated; both without gradient.

    Example:
        >>> m = torch.zeros(1, 3, 4, 4); m[0, 0, :2, :2] = 1; m[0, 1] = m[0, 0]
        >>> e = m[:, 0].clone()
        >>> marginal_presence_target(m, e, torch.full((1, 3), 4.0))[0].tolist()
        [[1.0, 0.0, 0.0]]
    """
    if masks.dim() != 4 or evidence.shape != (masks.shape[0], *masks.shape[2:]):
        raise ValueError(
            f"masks must be (B, N, H, W) and evidence (B, H, W), got {tuple(masks.shape)} "
            f"and {tuple(evidence.shape)}"
        )
    if area.shape != masks.shape[:2]:
        raise ValueError(f"area must be (B, N) = {tuple(masks.shape[:2])}, got {tuple(area.shape)}")
    B, N = masks.shape[:2]
    m = masks.detach().clamp(0.0, 1.0).flatten(2)  # (B, N, P)
    e = evidence.detach().flatten(1)  # (B, P)
    a = area.detach().clamp_min(1.0)
    covered = torch.zeros_like(e)
    target = torch.zeros(B, N, dtype=m.dtype, device=m.device)
    gain = torch.zeros_like(target)
    pending = torch.ones(B, N, dtype=torch.bool, device=m.device)
    rows = torch.arange(B, device=m.device)
    if order is None:
        order = torch.zeros(B, N, dtype=m.dtype, device=m.device)
    order = order.detach().to(m.dtype)
    for _ in range(N):
        g = (m * (e * (1 - covered))[:, None]).sum(-1) / a  # (B, N)
        # most present first; ties (e.g. no presence given) broken by the larger gain
        key = order + 1e-3 * g.clamp(0, 1)
        best = key.masked_fill(~pending, -float("inf")).argmax(-1)  # (B,)
        g_best = g[rows, best]
        accept = g_best >= margin
        if max_on is not None:
            accept = accept & (target.sum(-1) < max_on)
        gain[rows, best] = g_best
        target[rows, best] = accept.to(m.dtype)
        pending[rows, best] = False
        picked = m[rows, best] * accept[:, None].to(m.dtype)  # (B, P)
        covered = covered + (1 - covered) * picked
    return target, gain


@torch.no_grad()
def ranked_presence_target(presence: Tensor, count: Tensor) -> Tensor:
    """The ``count`` most present windows are on (``prior_presence.target=hull``).

    Args:
        presence: (B, N) in [0, 1].
        count: (B,) how many windows to keep on (e.g. the individuals the label-free
            visual hull finds in the frame and view, :mod:`nsd.cues.occupancy`).

    Returns:
        (B, N) in {0, 1}, detached. Ties go to the lower window index.

    Example:
        >>> ranked_presence_target(torch.tensor([[0.2, 0.9, 0.5]]), torch.tensor([2])).tolist()
        [[0.0, 1.0, 1.0]]
    """
    N = presence.shape[-1]
    if count.shape != presence.shape[:1]:
        raise ValueError(f"count must be ({presence.shape[0]},), got {tuple(count.shape)}")
    order = torch.argsort(presence.detach(), dim=-1, descending=True, stable=True)
    rank = torch.empty_like(order)
    rank.scatter_(-1, order, torch.arange(N, device=order.device).expand_as(order))
    return (rank < count[:, None]).to(presence.dtype)


def smoothed_counts(valid: Tensor, window: int, scene_population: bool = False) -> Tensor:
    r"""Individuals in view per frame and view, from the visual hull's proposals.

    The hull's per-frame count flickers: a ghost component appears for a frame, and
    individuals that touch merge into one component. The number of individuals in view
    changes slowly, so per view the count is the running median over a centred window
    of ``window`` frames (edges: the nearest frame repeated), which removes changes
    shorter than half the window; ``window=1`` keeps the per-frame count.

    Individuals in close interaction can stay merged for longer than any window. With
    ``scene_population`` the scene is assumed to hold a constant population, the median
    over all frames of the frame's count :math:`n_t` (hull components in any view), and
    a view's count is raised by what the frame misses,
    :math:`c_{t,v} \leftarrow c_{t,v} + \max(0, \operatorname{median}_t n_t - \tilde n_t)`
    (:math:`\tilde n_t` the running median of :math:`n_t`). Do not use it for footage
    where individuals leave the scene for long.

    Args:
        valid: (T, V, k) bool, the valid hull proposals of every frame and view (slots
            shared across views: slot j is the same individual in every view).
        window: odd number of frames.
        scene_population: add the merged individuals back (see above).

    Returns:
        (T, V) int64.

    Example:
        >>> v = torch.tensor([2, 2, 1, 2, 2])[:, None, None] > torch.arange(3)
        >>> smoothed_counts(v, 3)[:, 0].tolist()
        [2, 2, 2, 2, 2]
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the count window must be an odd number of frames >= 1, got {window}")

    per_view = valid.sum(-1).cpu().numpy()
    frame = valid.any(1).sum(-1).cpu().numpy()
    if window > 1:
        per_view = median_filter(per_view, size=(window, 1), mode="nearest")
        frame_local = median_filter(frame, size=window, mode="nearest")
    else:
        frame_local = frame
    if scene_population:
        population = int(np.floor(np.median(frame) + 0.5))
        per_view = per_view + np.clip(population - frame_local, 0, None)[:, None]
    return torch.from_numpy(np.ascontiguousarray(per_view)).to(valid.device)


def presence_target_loss(presence: Tensor, target: Tensor) -> Tensor:
    """Mean binary cross-entropy of presences (B, N) in [0, 1] against detached targets."""
    return F.binary_cross_entropy(presence.clamp(1e-6, 1 - 1e-6), target.detach())
