"""The hull-only baseline: the decomposition that classical multi-view geometry gives alone.

No learning: per instant, the visual hull of the background residuals
(:func:`nsd.cues.occupancy.multiview_proposals`) gives ``k`` individuals; in each view an
individual's mask is the foreground pixels it owns, its depth is the hull's, and it is
the same individual in every view (the slot index), so cross-view association is the
hull's. Scored with exactly the metrics, frames and apart/touching split of a trained
decomposition (:func:`nsd.evaluation.decomposition.evaluate_model`), this row shows what
learning adds, and where.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nsd.cues.clustering import ClusterTrack, MixtureRules
from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence
from nsd.cues.holes import SPECKLE, Speckle
from nsd.cues.occupancy import VoxelGrid, multiview_proposals, scene_track
from nsd.evaluation.contact import touches
from nsd.evaluation.decomposition import (
    Tally,
    coco_ap,
    count_associations,
    instant_truth,
    score_views,
)

__all__ = ["HullDecomposition", "evaluate_hull", "hull_decomposition"]


@dataclass
class HullDecomposition:
    """The hull-only decomposition of one instant of V views, N = ``k`` slots.

    Attributes:
        masks, raw_masks: (V, N, H, W) float, 1 where the slot owns a foreground pixel.
        depths: (V, N) camera-space depths; scores: (V, N); active: (V, N) bool.
    """

    masks: Tensor
    raw_masks: Tensor
    depths: Tensor
    scores: Tensor
    active: Tensor


def hull_decomposition(
    images: Tensor,
    backgrounds: Tensor,
    grid: VoxelGrid,
    k: int,
    split: bool = True,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
    track: ClusterTrack | None = None,
    speckle: Speckle = SPECKLE,
) -> HullDecomposition:
    """Decompose one instant with the visual hull alone.

    Args:
        images, backgrounds: (V, 3, H, W) in [0, 1].
        grid: the hull's voxel grid of these cameras at this size.
        k: individuals (windows); ``split`` and ``track`` (carried from the previous
            instant) as :func:`nsd.cues.clustering.cluster_individuals`.
        speckle: the masks' speckle cleaned as the learned decomposition's
            (:class:`nsd.cues.holes.Speckle`).
    """
    ev = foreground_evidence(images, backgrounds, evidence_threshold, evidence_softness)
    hull = multiview_proposals(ev, grid, k, split=split, track=track)
    slots = torch.arange(k)[None, :, None, None]
    masks = speckle.clean_batch((hull.owners[:, None] == slots).float())
    return HullDecomposition(masks, masks, hull.depths, hull.valid.float(), hull.valid)


@torch.no_grad()
def evaluate_hull(
    data, frames: Sequence[int], gt, grid: VoxelGrid, k: int, split: bool = True,
    threshold: float = 0.5, evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS, rules: MixtureRules | None = None,
    speckle: Speckle = SPECKLE,
) -> dict[str, float]:
    """The metrics of :func:`nsd.evaluation.decomposition.evaluate_model` (without the
    novel-view ones) for the hull-only decomposition of ``frames`` of ``data``; ``rules``:
    when the hull's 3D mixture replaces its k-means (None: the shipped defaults); ``speckle``
    as :func:`hull_decomposition`."""
    tally = Tally()
    V = data.num_views
    # the frames in order, as decompose_views' instants; the mixture decided for the scene
    track = scene_track(lambda t: foreground_evidence(*data.views(t), evidence_threshold,
                                                      evidence_softness), frames, grid, k, split,
                         rules=rules)
    for t in frames:
        views, bgs = data.views(int(t))
        dec = hull_decomposition(views, bgs, grid, k, split, evidence_threshold,
                                 evidence_softness, track, speckle)
        truths = instant_truth(gt, data, int(t))
        counts = tally.counts(touches(truths))
        per_view = score_views(dec, truths, threshold, counts)
        tally.add_coco(dec, truths, threshold)
        for v in range(V):
            for w in range(V):
                if v != w:
                    count_associations(per_view[v], per_view[w], lambda i: i, counts)
    out = tally.metrics()
    out.update(coco_ap(gt.coco, tally.results, tally.image_ids))
    return {key: float(np.float64(val)) for key, val in out.items()}
