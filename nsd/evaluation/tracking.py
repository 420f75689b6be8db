"""Tracking metrics of an export against a synthetic scene: MOTA, MOTP, IDF1, ID switches.

Computed by motmetrics (py-motmetrics, the CLEAR-MOT and identity metrics of the
MOTChallenge benchmark), one sequence per camera, pooled over the cameras. Ground truth:
the visible boxes of the scene's ``gt/coco.json`` with their ``identity_id`` (boxes smaller
than ``min_area`` visible pixels are left out: nobody can track what no camera shows).
Predictions: the export's boxes (``subjects.coco.json``) with either their per-camera
track id (``subject_id``, what ``tracks/<cam>.txt`` holds) or any other id per row (the
final identities of ``identities.csv``). A match needs box IoU >= ``min_iou``.

HOTA (with its detection and association parts DetA, AssA, averaged over the localisation
thresholds 0.05 .. 0.95 of box IoU, as the HOTA paper) comes from TrackEval, the
MOTChallenge's reference implementation, its ``HOTA`` metric class fed the same boxes and
ids, one sequence per camera, combined as TrackEval combines sequences. TrackEval's package
metadata asks for the ``opencv-python`` wheel, a second OpenCV beside the toolkit's
``opencv-python-headless`` (its HOTA code uses none), so ``tools/setup.sh`` installs it
without its dependencies; where it is missing, HOTA is NaN and said once.
"""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from pathlib import Path

import motmetrics as mm
import numpy as np

from nsd.ops.boxes import box_iou_xywh

__all__ = ["HOTA_METRICS", "TRACKING_METRICS", "hota", "tracking_metrics"]

log = logging.getLogger(__name__)

# motmetrics name -> our key
TRACKING_METRICS = {"mota": "mota", "motp": "motp_iou", "idf1": "idf1",
                    "num_switches": "id_switches", "recall": "recall", "precision": "precision",
                    "num_frames": "camera_frames"}


HOTA_METRICS = ("hota", "deta", "assa")


def hota(sequences: list[dict]) -> dict[str, float]:
    """HOTA, DetA and AssA of sequences (TrackEval's ``HOTA``, combined over sequences).

    Args:
        sequences: per sequence, ``gt_ids`` and ``tracker_ids`` (lists over frames of int
            arrays) and ``similarity`` (list of (n_gt, n_tracker) box IoU arrays).

    Returns:
        ``hota``, ``deta``, ``assa`` in [0, 1] (means over the localisation thresholds);
        NaN without TrackEval.
    """
    try:
        from trackeval.metrics import HOTA  # optional: installed by tools/setup.sh
    except ImportError:
        log.warning("HOTA needs TrackEval (tools/setup.sh installs it; by hand: "
                    "pip install --no-deps trackeval): HOTA, DetA, AssA are NaN")
        return dict.fromkeys(HOTA_METRICS, float("nan"))
    metric, results = HOTA({"PRINT_CONFIG": False}), {}
    for k, seq in enumerate(sequences):
        data: dict = {"gt_ids": [], "tracker_ids": [], "similarity_scores": seq["similarity"]}
        for key, src in (("gt", "gt_ids"), ("tracker", "tracker_ids")):
            ids = sorted({int(i) for frame in seq[src] for i in frame})
            index = {i: j for j, i in enumerate(ids)}  # TrackEval wants ids 0 .. n - 1
            data[src] = [np.array([index[int(i)] for i in frame], int) for frame in seq[src]]
            data[f"num_{key}_ids"] = len(ids)
            data[f"num_{key}_dets"] = sum(len(frame) for frame in seq[src])
        results[str(k)] = metric.eval_sequence(data)
    if not results:
        return dict.fromkeys(HOTA_METRICS, float("nan"))
    res = metric.combine_sequences(results)
    return {"hota": float(np.mean(res["HOTA"])), "deta": float(np.mean(res["DetA"])),
            "assa": float(np.mean(res["AssA"]))}


def _boxes(coco: dict, key: str, min_area: float = 0.0) -> dict[tuple[str, int], list]:
    """(camera, frame) -> [(id, [x, y, w, h])] of a COCO file's annotations."""
    images = {int(im["id"]): (im["camera"], int(im["frame"])) for im in coco["images"]}
    out: dict[tuple[str, int], list] = defaultdict(list)
    for a in coco["annotations"]:
        if a.get("area", 1.0) >= min_area and a["bbox"][2] > 0 and a["bbox"][3] > 0:
            out[images[int(a["image_id"])]].append((a[key], a["bbox"], int(a["id"])))
    return out


def tracking_metrics(export: str | Path, scene: str | Path,
                     row_ids: dict[int, int] | None = None, min_iou: float = 0.5,
                     min_area: float = 16.0) -> dict[str, float]:
    """MOT metrics of an export against a synthetic scene.

    Args:
        export: nsd-export folder (``subjects.coco.json``).
        scene: the scene folder (``gt/coco.json``).
        row_ids: annotation id -> predicted id (e.g. the final identities); default: each
            row's per-camera track (``subject_id``). Rows without an id are left out.
        min_iou: box IoU a match needs.
        min_area: ground-truth boxes with fewer visible pixels are left out.

    Returns:
        ``mota``, ``motp_iou`` (mean IoU of matches), ``idf1``, ``id_switches``, ``recall``,
        ``precision``, ``camera_frames`` (pooled over the cameras) and ``hota``, ``deta``,
        ``assa`` (:func:`hota`; every box IoU counts there, ``min_iou`` does not apply).
    """
    gt = _boxes(json.loads((Path(scene) / "gt" / "coco.json").read_text()), "identity_id",
                min_area)
    pred = _boxes(json.loads((Path(export) / "subjects.coco.json").read_text()), "subject_id")
    frames = sorted({k for k in pred} | {k for k in gt if k[0] in {c for c, _ in pred}})
    accs, names, sequences = [], [], []
    for camera in sorted({c for c, _ in frames}):
        acc = mm.MOTAccumulator(auto_id=False)
        seq: dict[str, list] = {"gt_ids": [], "tracker_ids": [], "similarity": []}
        for cam, t in frames:
            if cam != camera:
                continue
            g = gt.get((cam, t), [])
            p, seen = [], set()
            for i, b, a in pred.get((cam, t), []):
                pid = i if row_ids is None else row_ids.get(a)
                if pid is not None and pid not in seen:  # one box per id and frame
                    seen.add(pid)
                    p.append((pid, b, a))
            # 1 - IoU, NaN (no match) below min_iou; our IoU: motmetrics 1.4's iou_matrix
            # calls np.asfarray, which NumPy 2 removed
            iou = box_iou_xywh([b for _, b, _ in g], [b for _, b, _ in p])
            seq["gt_ids"].append([i for i, _, _ in g])
            seq["tracker_ids"].append([i for i, _, _ in p])
            seq["similarity"].append(np.asarray(iou, np.float64).reshape(len(g), len(p)))
            dist = 1.0 - iou
            dist[dist > 1.0 - min_iou] = np.nan
            acc.update([i for i, _, _ in g], [i for i, _, _ in p], dist, frameid=t)
        accs.append(acc)
        names.append(camera)
        sequences.append(seq)
    if not accs:
        return {v: float("nan") for v in (*TRACKING_METRICS.values(), *HOTA_METRICS)}
    summary = mm.metrics.create().compute_many(
        accs, metrics=list(TRACKING_METRICS), names=names, generate_overall=True)
    row = summary.loc["OVERALL"]
    out = {ours: float(row[theirs]) for theirs, ours in TRACKING_METRICS.items()}
    out["motp_iou"] = 1.0 - out["motp_iou"]  # motmetrics reports the mean distance 1 - IoU
    out.update(hota(sequences))
    return out
