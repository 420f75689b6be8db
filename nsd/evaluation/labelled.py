"""An export scored against a user's labelled keypoints: evaluation on real footage.

Without ground-truth masks, a user's few labelled frames (SLEAP, DeepLabCut:
:mod:`nsd.io.labels`) still say whether the masks hold the right bodies and whether the
identities agree across cameras. In every labelled camera-frame, the labelled instances
and the exported subjects are matched one-to-one (Hungarian) on the number of an instance's
labelled keypoints inside a subject's visible mask; then

* ``keypoints_in_mask``: the share of all labelled keypoints (inside the image) that lie
  in the mask of the subject their instance was matched to (unmatched instances: none);
* ``detected``: the share of labelled instances matched to a subject holding at least one
  of their keypoints;
* ``cross_view_identity`` (labels with individuals named across cameras): over every pair
  of matched instances of one frame in two cameras, the share where the export agrees
  with the labels: the same individual has the same id, different individuals have
  different ids (ids: the final identities when given, else the rows' ``subject_id``).
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from itertools import combinations
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

from nsd.io.labels import Labels2D

__all__ = ["LABEL_METRICS", "score_labels"]

LABEL_METRICS = ("keypoints_in_mask", "detected", "cross_view_identity", "labelled_instances",
                 "labelled_camera_frames", "cross_view_pairs")


def score_labels(export: str | os.PathLike, labels: Labels2D,
                 row_ids: dict[int, int] | None = None) -> dict[str, float]:
    """The export's masks and identities against labelled keypoints (module docstring).

    Args:
        export: an ``nsd-export`` folder.
        labels: labelled 2D keypoints of the export's scene.
        row_ids: annotation id -> identity; default: each row's ``subject_id``.

    Returns:
        :data:`LABEL_METRICS` (NaN where nothing was there to score).
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    images = {int(im["id"]): im for im in coco["images"]}
    rows: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for a in coco["annotations"]:
        im = images[int(a["image_id"])]
        rows[(im["camera"], int(im["frame"]))].append(a)
    exported = {(im["camera"], int(im["frame"])): im for im in images.values()}
    inside = total = matched = instances = frames = 0
    ids: dict[int, dict[tuple[str, str], int]] = defaultdict(dict)  # frame -> (cam, who) -> id
    for (cam, frame), who_points in labels.points.items():
        if (cam, frame) not in exported or not who_points:
            continue
        frames += 1
        im = exported[(cam, frame)]
        W, H = int(im["width"]), int(im["height"])
        subjects = rows.get((cam, frame), [])
        masks = [mask_utils.decode(a["segmentation"]).astype(bool) for a in subjects]
        who = list(who_points)
        counts = np.zeros((len(subjects), len(who)))
        for g, name in enumerate(who):
            p = who_points[name]
            ok = np.isfinite(p).all(1)
            x, y = np.round(p[ok, 0]).astype(int), np.round(p[ok, 1]).astype(int)
            keep = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            total += int(keep.sum())
            for r, m in enumerate(masks):
                counts[r, g] = m[y[keep], x[keep]].sum()
        instances += len(who)
        if not subjects:
            continue
        for r, g in zip(*linear_sum_assignment(-counts), strict=True):
            if counts[r, g] > 0:
                inside += int(counts[r, g])
                matched += 1
                a = subjects[r]
                ident = (row_ids or {}).get(int(a["id"]), -1) if row_ids is not None \
                    else int(a["subject_id"])
                if ident >= 0:
                    ids[frame][(cam, who[g])] = ident
    agree = pairs = 0
    if labels.tracked:
        for per_frame in ids.values():
            for (ca, wa), (cb, wb) in combinations(per_frame, 2):
                if ca != cb:
                    pairs += 1
                    agree += (wa == wb) == (per_frame[(ca, wa)] == per_frame[(cb, wb)])
    nan = float("nan")
    return {"keypoints_in_mask": inside / total if total else nan,
            "detected": matched / instances if instances else nan,
            "cross_view_identity": agree / pairs if pairs else nan,
            "labelled_instances": float(instances), "labelled_camera_frames": float(frames),
            "cross_view_pairs": float(pairs)}
