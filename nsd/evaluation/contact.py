"""Apart and touching instants: the split of every decomposition metric.

The visual hull merges individuals that touch, so a metric averaged over a whole
sequence hides where a decomposition fails. Every evaluation therefore also reports
its metrics over the instants (all cameras at one frame) where individuals are
*apart* and those where they *touch*.

Two individuals are **in contact** at an instant when their ground-truth amodal
masks overlap (at least :data:`MIN_OVERLAP` pixels) in more than half of the cameras
that see both of them. One camera seeing one individual behind the other is
occlusion, not contact: from most other directions two separate bodies are seen
apart, while two bodies that touch overlap from almost every direction. An instant
is **touching** when at least one pair is in contact, else **apart**.

The definition uses the ground truth only, so the split is the same for every model
and for the hull-only baseline (:mod:`nsd.evaluation.hull_baseline`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

__all__ = ["MIN_OVERLAP", "PARTS", "pairs_in_contact", "touches", "touching_instants"]

MIN_OVERLAP = 4  # pixels of amodal overlap in one camera (as the depth-order metric's)
PARTS = ("apart", "touching")  # the two parts of every split metric


def pairs_in_contact(
    views: Sequence[tuple[Sequence[int], np.ndarray]], min_overlap: int = MIN_OVERLAP
) -> set[tuple[int, int]]:
    """The pairs of individuals in contact at one instant.

    Args:
        views: per camera, the identities (G,) of the individuals it sees and their
            amodal masks (G, H, W) bool.
        min_overlap: pixels of amodal overlap that make a camera see a pair overlap.

    Returns:
        pairs ``(a, b)`` of identities, ``a < b``, that overlap in more than half of
        the cameras seeing both.
    """
    seen: dict[tuple[int, int], int] = {}
    overlapping: dict[tuple[int, int], int] = {}
    for ids, amodal in views:
        ids = [int(i) for i in ids]
        if len(ids) < 2:
            continue
        flat = np.asarray(amodal, dtype=bool).reshape(len(ids), -1).astype(np.int64)
        inter = flat @ flat.T  # (G, G) overlap pixels
        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                pair = (min(ids[a], ids[b]), max(ids[a], ids[b]))
                seen[pair] = seen.get(pair, 0) + 1
                overlapping[pair] = overlapping.get(pair, 0) + int(inter[a, b] >= min_overlap)
    return {p for p, n in seen.items() if 2 * overlapping[p] > n}


def touching_instants(
    gt, cameras: Sequence[str], frames: Iterable[int], size: tuple[int, int] | None = None
) -> dict[int, bool]:
    """Frame index -> whether individuals touch at that instant.

    Args:
        gt: a :class:`nsd.io.ground_truth.GroundTruth`.
        cameras: the cameras of the instant.
        frames: frame indices.
        size: (H, W) at which the masks are compared (None: native).
    """
    return {int(t): touches([gt.frame(cam, int(t), size) for cam in cameras]) for t in frames}


def touches(views: Sequence) -> bool:
    """Whether individuals touch at one instant, from each camera's
    :class:`nsd.io.ground_truth.FrameGT` (``identity``, ``amodal``)."""
    return bool(pairs_in_contact([(f.identity, f.amodal) for f in views]))
