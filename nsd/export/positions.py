"""World positions of the exported individuals: their visible masks' centroids triangulated.

For every exported row the centroid of its visible mask (native pixels); for every
individual and frame (rows of one frame sharing an identity, or a ``subject_id`` where no
identity is given) the point nearest to the rays through its views' centroids
(:func:`nsd.cues.triangulation.nearest_point_to_rays`, lens distortion undone). One view
gives no position. The centroid of what a camera sees is not the body's centre when the
body is partly hidden, so a position is a trajectory point, not a keypoint.

``positions.csv`` (the identities stage of ``nsd-run``): ``frame``, ``identity`` (or
``subject_id``), ``x``, ``y``, ``z`` (metres, the calibration's world) and ``views``.
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections import defaultdict
from collections.abc import Collection, Mapping
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils

from nsd.cameras.calibration import CameraRig
from nsd.core.atomic import atomic_write_text
from nsd.cues.triangulation import nearest_point_to_rays

__all__ = ["POSITION_COLUMNS", "mask_centroid", "mask_centroids", "point_from_views",
           "read_positions", "triangulate_positions", "write_positions"]

POSITION_COLUMNS = ("frame", "identity", "x", "y", "z", "views")


def mask_centroid(mask: np.ndarray) -> np.ndarray | None:
    """Centroid (x, y) of an (H, W) mask in pixels (pixel centres at integers); None if empty."""
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()]) if len(xs) else None


def mask_centroids(coco: dict) -> dict[int, np.ndarray]:
    """Annotation id -> centroid (x, y) of its visible mask in native pixels; rows with an
    empty mask are left out."""
    out = {}
    for a in coco["annotations"]:
        c = mask_centroid(mask_utils.decode(a["segmentation"]))
        if c is not None:
            out[int(a["id"])] = c
    return out


def triangulate_positions(
    export: str | os.PathLike, rig: CameraRig, row_ids: dict[int, int] | None = None,
    frames: Collection[int] | None = None, centroids: Mapping[int, np.ndarray] | None = None,
) -> dict[tuple[int, int], tuple[np.ndarray, int]]:
    """World position of every individual and frame with at least two views.

    Args:
        export: an ``nsd-export`` folder (``subjects.coco.json``).
        rig: the scene's calibration at the footage's native size, in metres.
        row_ids: annotation id -> identity (>= 0; others are left out); default: each row's
            ``subject_id``.
        frames: only these frames (default: all; only their masks are decoded).
        centroids: :func:`mask_centroids` of this export, if already computed (no mask is
            decoded again: a second grouping of the same rows costs no decode).

    Returns:
        ``(frame, id)`` -> (position (3,) float64, number of views).
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    if frames is not None:
        wanted = {int(f) for f in frames}
        coco = {**coco, "annotations": [a for a in coco["annotations"]
                                        if int(a["frame"]) in wanted]}
    if centroids is None:
        centroids = mask_centroids(coco)
    groups: dict[tuple[int, int], list[tuple[str, np.ndarray]]] = defaultdict(list)
    for a in coco["annotations"]:
        aid = int(a["id"])
        key = int(a["subject_id"]) if row_ids is None else row_ids.get(aid, -1)
        if key >= 0 and aid in centroids:
            groups[(int(a["frame"]), key)].append((a["camera"], centroids[aid]))
    out = {}
    for key, views in groups.items():
        cams = {}
        for camera, uv in views:  # one ray per camera (two rows of one id: their mean)
            cams.setdefault(camera, []).append(uv)
        point = point_from_views(rig, {c: np.mean(uv, 0) for c, uv in cams.items()})
        if point is not None:
            out[key] = (point, len(cams))
    return out


def point_from_views(rig: CameraRig, pixels: dict[str, np.ndarray]) -> np.ndarray | None:
    """The world point (3,) nearest to the rays through one pixel (x, y) per camera (native
    pixels, lens distortion undone), or None with fewer than two cameras or parallel rays."""
    if len(pixels) < 2:
        return None
    origins = np.stack([rig[c].center for c in pixels])
    rays = np.stack([rig[c].unproject(np.asarray(uv, np.float64)[None])[0]
                     for c, uv in pixels.items()])
    try:
        return nearest_point_to_rays(origins, rays)
    except ValueError:  # parallel rays
        return None


def write_positions(path: Path, positions: dict[tuple[int, int], tuple[np.ndarray, int]]) -> None:
    """``positions.csv`` (module docstring), sorted by frame and id, atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(POSITION_COLUMNS)
    for (frame, ident), (xyz, views) in sorted(positions.items()):
        w.writerow([frame, ident, *(f"{v:.6f}" for v in xyz), views])
    atomic_write_text(path, buf.getvalue())


def read_positions(path: Path) -> dict[tuple[int, int], tuple[np.ndarray, int]]:
    """What :func:`write_positions` wrote."""
    with Path(path).open(newline="") as f:
        return {(int(r["frame"]), int(r["identity"])): (
            np.array([float(r["x"]), float(r["y"]), float(r["z"])]), int(r["views"]))
            for r in csv.DictReader(f)}
