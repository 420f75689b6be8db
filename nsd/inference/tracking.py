"""Subject ids that stay the same over time: linking each frame's subjects to tracks.

NSD's association (:func:`nsd.inference.single.associate_views`) gives the windows of
one frame cross-view subject ids, but those ids are per frame: subject 0 of
frame t need not be subject 0 of frame t+1. :class:`SubjectTracker` links the
subjects of consecutive frames into tracks with a deliberately simple rule:

* a subject of frame t is described by the mean of its views' unit appearance
  vectors (the association dims, as in training), its box in each camera and, where two
  or more cameras see it, its world position (the point nearest to the rays through its
  boxes' centres);
* the similarity of a track and a subject is
  ``appearance_weight * cos(a_track, a_subject) + (1 - appearance_weight) * IoU``
  where IoU is the mean box IoU over the cameras that see both (0 if none); when both
  have a position, ``position_weight`` of it goes to
  ``exp(-d^2 / (2 position_scale^2))`` instead, ``d`` the distance between them. In a
  huddle the boxes of neighbours overlap in every camera, so box IoU links a track to
  whoever took its place; where they stand tells them apart;
* tracks and subjects are matched one-to-one by the Hungarian algorithm on this
  similarity; pairs below ``min_similarity`` are not linked;
* an unlinked subject starts a new track; a track unseen for more than
  ``max_gap`` frames is closed (its id is never reused). A track's description
  is its last observation (no motion model, no smoothing).

Track ids start at 1 (MOTChallenge ids are positive).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from nsd.cameras.calibration import CameraRig
from nsd.cues.occupancy import working_volume
from nsd.ops.boxes import box_iou_xywh
from nsd.ops.vectors import unit_vectors

__all__ = ["SubjectObservation", "SubjectTracker", "position_scale", "track_similarity"]


def position_scale(setting: float | str, rig: CameraRig, resolution: int) -> float:
    """A distance between world positions that matters to tracking (the export's
    ``tracking.position_scale``, the identities' ``jump``): ``setting`` in metres as given, or
    ``auto``: two sides of a voxel of the hull's grid of ``resolution`` voxels per side (a
    fraction of the working volume, whatever the scene's size)."""
    if setting == "auto":
        _, half, _ = working_volume(rig)
        return 2 * (2 * half / int(resolution))
    return float(setting)


@dataclass
class SubjectObservation:
    """One subject of one frame, seen in one or more cameras.

    Attributes:
        appearance: unit appearance vector (D,) (mean of the views' unit vectors,
            renormalised).
        boxes: camera name -> COCO box [x, y, w, h] in that camera's pixels.
        position: world position (3,), or None (seen by one camera).
    """

    appearance: np.ndarray
    boxes: dict[str, np.ndarray] = field(default_factory=dict)
    position: np.ndarray | None = None


def track_similarity(
    a: SubjectObservation, b: SubjectObservation, appearance_weight: float,
    position_weight: float = 0.0, position_scale: float = 1.0,
) -> float:
    """Similarity of two observations: weighted cosine of appearance and mean box IoU, and
    their positions' closeness (module docstring)."""
    cos = float(np.dot(unit_vectors(a.appearance), unit_vectors(b.appearance)))
    common = [c for c in a.boxes if c in b.boxes]
    ious = [box_iou_xywh(a.boxes[c], b.boxes[c])[0, 0] for c in common]
    iou = float(np.mean(ious)) if common else 0.0
    sim = appearance_weight * cos + (1.0 - appearance_weight) * iou
    if position_weight > 0 and a.position is not None and b.position is not None:
        d2 = float(np.sum((np.asarray(a.position) - np.asarray(b.position)) ** 2))
        near = float(np.exp(-0.5 * d2 / position_scale**2))
        sim = (1.0 - position_weight) * sim + position_weight * near
    return sim


@dataclass
class _Track:
    id: int
    last: SubjectObservation
    last_frame: int


class SubjectTracker:
    """Link per-frame subjects into tracks (see the module docstring).

    Args:
        appearance_weight: weight of the appearance cosine (the rest goes to box IoU).
        min_similarity: smallest similarity that links a subject to a track.
        max_gap: frames a track may go unseen before it is closed.
        position_weight: share of the similarity given to the positions' closeness when
            both observations have one (0: appearance and boxes only).
        position_scale: distance (world units) at which closeness falls to exp(-1/2).

    Example:
        >>> trk = SubjectTracker()
        >>> box = np.array([10.0, 10.0, 20.0, 40.0])
        >>> o = SubjectObservation(np.array([1.0, 0.0]), {"cam0": box})
        >>> trk.update(0, {0: o}), trk.update(1, {5: o})
        ({0: 1}, {5: 1})
    """

    def __init__(
        self, appearance_weight: float = 0.5, min_similarity: float = 0.3, max_gap: int = 10,
        position_weight: float = 0.0, position_scale: float = 1.0,
    ) -> None:
        if not 0.0 <= appearance_weight <= 1.0:
            raise ValueError(f"appearance_weight must be in [0, 1], got {appearance_weight}")
        if not 0.0 <= position_weight <= 1.0 or position_scale <= 0:
            raise ValueError(f"position_weight must be in [0, 1] and position_scale > 0, got "
                             f"{position_weight}, {position_scale}")
        self.appearance_weight = appearance_weight
        self.position_weight, self.position_scale = position_weight, position_scale
        self.min_similarity = min_similarity
        self.max_gap = max_gap
        self.tracks: list[_Track] = []
        self.next_id = 1

    def update(self, frame: int, subjects: Mapping[int, SubjectObservation]) -> dict[int, int]:
        """Link the subjects of ``frame`` (key: per-frame subject id) to tracks.

        Frames must come in increasing order. Returns per-frame id -> track id.
        """
        self.tracks = [tr for tr in self.tracks if frame - tr.last_frame <= self.max_gap]
        keys = list(subjects)
        out: dict[int, int] = {}
        if self.tracks and keys:
            sim = np.array(
                [
                    [track_similarity(tr.last, subjects[k], self.appearance_weight,
                                      self.position_weight, self.position_scale)
                     for k in keys]
                    for tr in self.tracks
                ]
            )
            rows, cols = linear_sum_assignment(-sim)
            for r, c in zip(rows, cols, strict=True):
                if sim[r, c] >= self.min_similarity:
                    tr, obs = self.tracks[r], subjects[keys[c]]
                    if obs.position is None and tr.last.position is not None:
                        obs = replace(obs, position=tr.last.position)  # seen by one camera
                    tr.last, tr.last_frame = obs, frame
                    out[keys[c]] = tr.id
        for k in keys:
            if k not in out:
                self.tracks.append(_Track(self.next_id, subjects[k], frame))
                out[k] = self.next_id
                self.next_id += 1
        return out
