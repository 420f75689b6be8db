r"""Proposal and association priors: windows pulled to label-free proposals.

Proposals come from :mod:`nsd.cues.proposals` (single view) or the visual hull
(:mod:`nsd.cues.occupancy`, multi-view, where slot j of every view is one individual).

The *proposal prior* pulls each detector window towards its Hungarian-matched
proposal (squared error on centre and log scale). It seeds localisation,
which Bi-NVS alone finds only after many GPU iterations (NSD: ~200k), and is
annealed to zero over ``decay_steps`` so the decomposition is then shaped by
re-synthesis alone. It uses no labels.

The *association prior* pulls the soft association towards the proposals' identities:
two windows of different views show the same individual when they are matched to the
same multi-view proposal slot.
"""

from __future__ import annotations

from torch import Tensor

from nsd.cues.proposals import _cost, match_proposals

__all__ = ["association_prior", "proposal_prior"]


def proposal_prior(
    boxes: Tensor, proposals: Tensor, valid: Tensor, matching: Tensor | None = None
) -> Tensor:
    """Squared error between windows and their matched valid proposals.

    Args:
        boxes: detector windows (B, N, 4).
        proposals: (B, N, 4) (slot j of every view is the same individual for
            multi-view proposals).
        valid: (B, N) bool.
        matching: (B, N) from :func:`match_proposals` (computed if None).

    Returns:
        Mean over matched pairs of |t - t*|^2 + |log s - log s*|^2 (0 if none is valid).
    """
    if matching is None:
        matching = match_proposals(boxes, proposals, valid)
    c = _cost(boxes, proposals) * valid[:, None, :]
    matched = c.gather(2, matching[..., None])[..., 0]
    return matched.sum() / valid.sum().clamp_min(1)


def association_prior(
    association: Tensor,
    matching_target: Tensor,
    valid_target: Tensor,
    matching_source: Tensor,
    valid_source: Tensor,
) -> Tensor:
    """Cross-entropy pulling the soft association towards multi-view proposal identities.

    Target window j and source window i show the same individual when they are
    matched to the same proposal slot (multi-view proposals share slots across
    views).

    Args:
        association: soft association (B, N, M), rows target windows.
        matching_target, matching_source: proposal slot of each window (B, N), (B, M).
        valid_target, valid_source: validity of those proposals (B, N), (B, M).
    """
    vt = valid_target.gather(1, matching_target)
    vs = valid_source.gather(1, matching_source)
    same = (matching_target[:, :, None] == matching_source[:, None, :]) & vs[:, None, :]
    has = same.any(-1) & vt
    target = same.float().argmax(-1)
    logp = association.clamp_min(1e-8).log()
    nll = -logp.gather(2, target[..., None])[..., 0]
    return (nll * has).sum() / has.sum().clamp_min(1)
