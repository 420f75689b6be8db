"""Per-subject 3D keypoints of an export: which rows to fit, and the ``keypoints3d.npz`` file.

Both ways the end-to-end pipeline gets 3D keypoints (NeTePu inverse rendering of the
visible masks; NSD's pose regressor from a few labelled frames) fit one pose per subject
(cross-view ``subject_id``) and selected frame from that subject's rows, and write the
same file, which the texture-code step reads::

    keypoints3d.npz
      id          (n,)       annotation ids of the export (COCO ``id``, embeddings ``id``)
      keypoints   (n, K, 3)  world keypoints of each row's subject, the calibration's units
      subject_frame (m,), subject_id (m,), subject_keypoints (m, K, 3),
      subject_loss (m,), subject_views (m,)   one entry per fitted subject-frame
      subject_relabelled (m,)  bool: left and right swapped after the fit (the subject
                               faced against its travel, netepu.pipeline.travel)
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from nsd.core.atomic import atomic_save_npz

__all__ = ["SubjectKeypoints", "subject_groups"]


def subject_groups(
    export: str | os.PathLike, frame_step: int, keep: Callable[[dict, dict], bool]
) -> tuple[dict[int, dict], list[tuple[tuple[int, int], list[dict]]], int]:
    """The COCO rows of every ``frame_step``-th exported frame, grouped by subject.

    Args:
        export: an ``nsd-export`` folder.
        frame_step: every this many exported frames (from the first).
        keep: ``(annotation, image) -> bool``, the rows to use.

    Returns:
        ``(images by id, [((frame, subject_id), annotations)] in that order, frames chosen)``.
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    images = {int(im["id"]): im for im in coco["images"]}
    frames = sorted({int(im["frame"]) for im in images.values()})
    chosen = set(frames[::frame_step])
    groups: dict[tuple[int, int], list[dict]] = defaultdict(list)
    for a in coco["annotations"]:
        im = images[int(a["image_id"])]
        if int(im["frame"]) in chosen and keep(a, im):
            groups[(int(im["frame"]), int(a["subject_id"]))].append(a)
    return images, sorted(groups.items()), len(chosen)


class SubjectKeypoints:
    """The fitted subject-frames, collected and written as ``keypoints3d.npz``."""

    def __init__(self) -> None:
        self.row_ids: list[int] = []
        self.row_keypoints: list[np.ndarray] = []
        self.subjects: dict[str, list] = defaultdict(list)

    def __len__(self) -> int:
        return len(self.subjects["frame"])

    def add(self, frame: int, subject: int, rows: list[dict], keypoints, loss: float,
            relabelled: bool = False) -> None:
        """One subject-frame's world keypoints (K, 3), given to each of its ``rows``
        (``relabelled``: its left and right were swapped after the fit)."""
        kp = np.asarray(keypoints, np.float32)
        for a in rows:
            self.row_ids.append(int(a["id"]))
            self.row_keypoints.append(kp)
        for key, value in (("frame", frame), ("id", subject), ("keypoints", kp),
                           ("loss", loss), ("views", len(rows)),
                           ("relabelled", bool(relabelled))):  # fmt: skip
            self.subjects[key].append(value)

    def summary(self, frames: int, loss_name: str) -> dict[str, Any]:
        """Counts of what was fitted, and the mean of the per-subject ``loss`` as ``loss_name``.

        Example:
            >>> s = SubjectKeypoints()
            >>> s.summary(3, "mean_loss")
            {'subject_frames': 0, 'rows': 0, 'frames': 3, 'mean_loss': None}
        """
        losses = self.subjects["loss"]
        return {
            "subject_frames": len(self),
            "rows": len(self.row_ids),
            "frames": frames,
            loss_name: float(np.mean(losses)) if losses else None,
        }

    def save(self, path: str | os.PathLike, k: int) -> None:
        """Write the file atomically (``k``: keypoints per pose, for empty files too)."""
        s = self.subjects
        atomic_save_npz(
            Path(path),
            id=np.asarray(self.row_ids, np.int64),
            keypoints=np.asarray(self.row_keypoints, np.float32).reshape(-1, k, 3),
            subject_frame=np.asarray(s["frame"], np.int64),
            subject_id=np.asarray(s["id"], np.int64),
            subject_keypoints=np.asarray(s["keypoints"], np.float32).reshape(-1, k, 3),
            subject_loss=np.asarray(s["loss"], np.float32),
            subject_views=np.asarray(s["views"], np.int64),
            subject_relabelled=np.asarray(s["relabelled"], bool),
        )
