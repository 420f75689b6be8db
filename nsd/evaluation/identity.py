"""Identity accuracy of an export's rows against a synthetic scene's ground truth.

The identities themselves come from the re-identification step of the pipeline, or from any
other source.

Accuracy (:func:`identity_accuracy`, synthetic scenes with ``gt/``): every
exported row is matched to a ground-truth visible mask of its camera-frame
(Hungarian on mask IoU, IoU >= 0.5); then

* ``identity_accuracy``: rows (those given an identity) whose identity maps to their ground-truth
  individual under the best one-to-one mapping of identities to individuals;
* ``cross_view_accuracy``: pairs of rows of the same frame and different
  cameras whose "same identity" agrees with "same individual";
* ``cross_time_accuracy``: the same for pairs of rows of the same camera ten or
  more frames apart (a random sample of at most 20,000 pairs).
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Collection
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

from nsd.evaluation.contact import touching_instants
from nsd.io.ground_truth import GroundTruth
from nsd.ops.boxes import mask_iou

__all__ = ["ground_truth_identities", "identity_accuracy", "identity_accuracy_by_contact"]


def ground_truth_identities(
    export: str | Path, scene: str | Path, min_iou: float = 0.5,
    frames: Collection[int] | None = None,
) -> dict[int, tuple[str, int, int, int]]:
    """Annotation id -> (camera, frame, subject_id, ground-truth identity) of the exported rows
    that match a visible ground-truth mask of their camera-frame (Hungarian on mask IoU);
    ``frames``: only the rows of these frames (None: all; the ground truth of the others is
    not read)."""

    gt = GroundTruth.load(scene)
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    images = {int(im["id"]): im for im in coco["images"]}
    by_image = defaultdict(list)
    for a in coco["annotations"]:
        by_image[int(a["image_id"])].append(a)
    out = {}
    for iid, anns in by_image.items():
        im = images[iid]
        if frames is not None and int(im["frame"]) not in frames:
            continue
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
    row_ids: np.ndarray,
    identity: np.ndarray,
    min_iou: float = 0.5,
    seed: int = 0,
    touching: dict[int, bool] | None = None,
) -> dict[str, float]:
    """Identity accuracy of an export's rows against a synthetic scene (see the module).

    Args:
        row_ids: (R,) annotation ``id`` of the rows to score (others are not scored).
        identity: (R,) their identities.
        touching: frame -> whether individuals touch then (:mod:`nsd.evaluation.contact`);
            adds ``identity_accuracy_apart`` and ``identity_accuracy_touching``: the rows of
            each part that the one best mapping of all rows gets right.
    """

    matched = ground_truth_identities(export, scene, min_iou)
    given = dict(zip(np.asarray(row_ids).tolist(), np.asarray(identity).tolist(), strict=True))
    rows = [(cam, t, given[a], true) for a, (cam, t, _, true) in matched.items() if a in given]
    if not rows:
        return {"matched_rows": 0.0}
    pred_id = np.array([r[2] for r in rows])
    true_id = np.array([r[3] for r in rows])
    P, T = np.unique(pred_id), np.unique(true_id)
    counts = np.array([[np.sum((pred_id == p) & (true_id == t)) for t in T] for p in P])
    pr, tc = linear_sum_assignment(-counts)
    acc = float(counts[pr, tc].sum() / len(rows))
    mapped = dict(zip(P[pr].tolist(), T[tc].tolist(), strict=True))
    right = np.array([mapped.get(p, None) == t for p, t in zip(pred_id.tolist(), true_id.tolist(),
                                                                 strict=True)])
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
    split = {}
    if touching is not None:
        part = np.array([bool(touching.get(int(t), False)) for t in frames])
        for name, sel in (("apart", ~part), ("touching", part)):
            split[f"identity_accuracy_{name}"] = (
                float(right[sel].mean()) if sel.any() else float("nan"))
    return {
        "matched_rows": float(len(rows)),
        "identity_accuracy": acc,
        **split,
        "cross_view_accuracy": (
            float(agree[cross_view].mean()) if cross_view.any() else float("nan")
        ),
        "cross_time_accuracy": (
            float(((pred_id[a] == pred_id[b]) == (true_id[a] == true_id[b])).mean())
            if len(a)
            else float("nan")
        ),
    }


def identity_accuracy_by_contact(
    export: str | Path, scene: str | Path, table: dict, identity: np.ndarray,
    size: tuple[int, int] | None = None,
) -> dict[str, float]:
    """:func:`identity_accuracy` of the rows of ``table`` (columns ``id``, ``camera``,
    ``frame``), split apart / touching by :func:`nsd.evaluation.contact.touching_instants`
    over the table's cameras and frames, with masks compared at ``size`` (H, W) as the
    decomposition's evaluation does (None: native)."""
    cameras = sorted(set(np.asarray(table["camera"]).tolist()))
    frames = sorted({int(t) for t in np.asarray(table["frame"]).tolist()})
    touching = touching_instants(GroundTruth.load(scene), cameras, frames, size)
    return identity_accuracy(export, scene, table["id"], identity, touching=touching)
