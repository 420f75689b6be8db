"""Identities across cameras and time from texture codes, and their accuracy against ground truth.

``nsd-export`` gives every subject a track id (``subject_id``: the cross-view
association of a frame, linked over time by box overlap and appearance). A
track can break (an occlusion, a subject leaving the view) and two tracks can
be the same individual. Here each track is described by the mean of its rows'
unit texture codes (NeTePu's :math:`\\mu` from the visible pixels only, see
``netepu-embed``), and tracks are grouped into ``k`` identities by average-
linkage agglomerative clustering on the cosine distance that never joins two
tracks seen in the same frame (so more than ``k`` identities remain when the
tracks do not allow fewer). ``k`` is
the number of individuals the export shows at once (the median over frames of
the distinct subjects per frame) unless given. With one subject (k = 1) no
association is needed and every track is identity 0.

Accuracy (:func:`identity_accuracy`, synthetic scenes with ``gt/``): every
exported row is matched to a ground-truth visible mask of its camera-frame
(Hungarian on mask IoU, IoU >= 0.5); then

* ``identity_accuracy``: rows whose identity maps to their ground-truth
  individual under the best one-to-one mapping of identities to individuals;
* ``cross_view_accuracy``: pairs of rows of the same frame and different
  cameras whose "same identity" agrees with "same individual";
* ``cross_time_accuracy``: the same for pairs of rows of the same camera ten or
  more frames apart (a random sample of at most 20,000 pairs).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "assign_identities",
    "constrained_average_linkage",
    "ground_truth_identities",
    "identity_accuracy",
]


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def constrained_average_linkage(dist: np.ndarray, apart: np.ndarray, k: int) -> np.ndarray:
    """Average-linkage clustering of T items into (at least) ``k`` clusters, never joining two
    items marked ``apart`` (T, T) bool; fewer merges are made if the constraints forbid them.

    Returns:
        labels (T,) in [0, clusters), numbered by first appearance.
    """
    clusters = [[i] for i in range(len(dist))]
    while len(clusters) > k:
        best, pair = np.inf, None
        for a in range(len(clusters)):
            for b in range(a + 1, len(clusters)):
                if apart[np.ix_(clusters[a], clusters[b])].any():
                    continue
                d = dist[np.ix_(clusters[a], clusters[b])].mean()
                if d < best:
                    best, pair = d, (a, b)
        if pair is None:
            break
        a, b = pair
        clusters[a] += clusters.pop(b)
    labels = np.empty(len(dist), np.int64)
    for j, members in enumerate(sorted(clusters, key=min)):
        labels[members] = j
    return labels


def assign_identities(
    table: dict[str, np.ndarray], column: str = "texture", k: int = 0
) -> tuple[dict[int, int], dict[str, Any]]:
    """Identity of every track of an export's embedding table.

    Args:
        table: columns ``subject_id``, ``frame`` and ``column`` (rows, D), optionally
            ``<column>_valid``.
        column: the texture-code column.
        k: identities (0: the median number of subjects per frame).

    Returns:
        ``({subject_id: identity}, summary)``. Tracks without a valid code are
        identity -1.
    """
    sid = np.asarray(table["subject_id"], np.int64)
    frame = np.asarray(table["frame"], np.int64)
    codes = np.asarray(table[column], np.float64)
    valid = np.asarray(table.get(f"{column}_valid", ~np.isnan(codes).any(1)), bool)
    per_frame = defaultdict(set)
    for s, t in zip(sid.tolist(), frame.tolist(), strict=True):
        per_frame[t].add(s)
    if k <= 0:
        k = max(
            1, round(float(np.median([len(v) for v in per_frame.values()]))) if per_frame else 1
        )
    tracks = sorted({int(s) for s in sid[valid]})
    out = {int(s): -1 for s in np.unique(sid)}
    if not tracks:
        return out, {"identities": 0, "tracks": 0, "k": k, "association": "no texture codes"}
    if k == 1 or len(tracks) == 1:
        out.update({s: 0 for s in tracks})
        return out, {
            "identities": 1,
            "tracks": len(tracks),
            "k": k,
            "association": "skipped: one subject",
        }
    desc = np.stack([_unit(_unit(codes[valid & (sid == s)]).mean(0)) for s in tracks])
    dist = np.clip(1 - desc @ desc.T, 0, 2)
    index = {s: i for i, s in enumerate(tracks)}
    apart = np.zeros(dist.shape, bool)
    for members in per_frame.values():
        m = [index[s] for s in members if s in index]
        apart[np.ix_(m, m)] = True
    np.fill_diagonal(apart, False)
    labels = constrained_average_linkage(dist, apart, k)
    out.update({s: int(labels[i]) for s, i in index.items()})
    return out, {
        "identities": len(set(labels.tolist())),
        "tracks": len(tracks),
        "k": k,
        "association": f"clustered by {column}",
    }


def ground_truth_identities(
    export: str | Path, scene: str | Path, min_iou: float = 0.5
) -> dict[int, tuple[str, int, int, int]]:
    """Annotation id -> (camera, frame, subject_id, ground-truth identity) of the exported rows
    that match a visible ground-truth mask of their camera-frame (Hungarian on mask IoU)."""
    import json

    from pycocotools import mask as mask_utils
    from scipy.optimize import linear_sum_assignment

    from nsd.evaluation import mask_iou
    from nsd.ground_truth import GroundTruth

    gt = GroundTruth.load(scene)
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    images = {int(im["id"]): im for im in coco["images"]}
    by_image = defaultdict(list)
    for a in coco["annotations"]:
        by_image[int(a["image_id"])].append(a)
    out = {}
    for iid, anns in by_image.items():
        im = images[iid]
        g = gt.frame(im["camera"], int(im["frame"]))
        if not len(g.identity):
            continue
        pred = np.stack([mask_utils.decode(a["segmentation"]).astype(bool) for a in anns])
        iou = mask_iou(pred, g.visible)
        r, c = linear_sum_assignment(-iou)
        for i, j in zip(r, c, strict=True):
            if iou[i, j] >= min_iou:
                a = anns[i]
                out[int(a["id"])] = (
                    im["camera"],
                    int(im["frame"]),
                    int(a["subject_id"]),
                    int(g.identity[j]),
                )
    return out


def identity_accuracy(
    export: str | Path,
    scene: str | Path,
    identities: dict[int, int],
    min_iou: float = 0.5,
    seed: int = 0,
) -> dict[str, float]:
    """Identity accuracy of an export's rows against a synthetic scene (see the module)."""
    from scipy.optimize import linear_sum_assignment

    matched = ground_truth_identities(export, scene, min_iou)
    rows = [(cam, t, identities.get(sid, -1), true) for cam, t, sid, true in matched.values()]
    if not rows:
        return {"matched_rows": 0.0}
    pred_id = np.array([r[2] for r in rows])
    true_id = np.array([r[3] for r in rows])
    P, T = np.unique(pred_id), np.unique(true_id)
    counts = np.array([[np.sum((pred_id == p) & (true_id == t)) for t in T] for p in P])
    pr, tc = linear_sum_assignment(-counts)
    acc = float(counts[pr, tc].sum() / len(rows))
    cams = np.array([r[0] for r in rows])
    frames = np.array([r[1] for r in rows])
    same_pred = pred_id[:, None] == pred_id[None]
    same_true = true_id[:, None] == true_id[None]
    agree = same_pred == same_true
    cross_view = (frames[:, None] == frames[None]) & (cams[:, None] != cams[None])
    rng = np.random.default_rng(seed)
    a = rng.integers(0, len(rows), 200_000)
    b = rng.integers(0, len(rows), 200_000)
    keep = (cams[a] == cams[b]) & (np.abs(frames[a] - frames[b]) >= 10)
    a, b = a[keep][:20_000], b[keep][:20_000]
    return {
        "matched_rows": float(len(rows)),
        "identity_accuracy": acc,
        "cross_view_accuracy": (
            float(agree[cross_view].mean()) if cross_view.any() else float("nan")
        ),
        "cross_time_accuracy": (
            float(((pred_id[a] == pred_id[b]) == (true_id[a] == true_id[b])).mean())
            if len(a)
            else float("nan")
        ),
    }
