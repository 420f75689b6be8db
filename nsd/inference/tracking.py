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
  is its last observation (no motion model, no smoothing);
* at most ``max_tracks`` tracks are live (the export gives the model's number of windows:
  no frame holds more subjects than that). A subject left unlinked while that many are
  live takes, whatever its similarity, the most similar live track that no subject of its
  frame took (again a Hungarian assignment). Without the bound, one frame in which every
  link falls below ``min_similarity`` (a box that hugs a body moves with its limbs, a
  position jumps with it) opens a new track while the old one is still live, and the
  subjects then flip between the two: on the real 4-camera Pose2Sim demo
  (docs/scaling.md) 2 subjects per frame became 7 tracks in 100 frames; bounded, 2.
  Such a forced link may join two individuals, so each track is also cut into
  *tracklets* where it opened or was forced on (:attr:`SubjectTracker.tracklets`): what
  a link above ``min_similarity`` vouches for. The identities stage decides per tracklet
  (a forced link that joined two individuals must not carry one's identity to the other).

Track ids start at 1 (MOTChallenge ids are positive).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from nsd.cameras.calibration import CameraRig
from nsd.cues.occupancy import working_volume
from nsd.ops.boxes import box_iou_xywh
from nsd.ops.vectors import unit_vectors

__all__ = [
    "SubjectObservation", "SubjectTracker", "max_tracks", "position_scale", "track_similarity",
]


def position_scale(setting: float | str, rig: CameraRig, resolution: int) -> float:
    """A distance between world positions that matters to tracking (the export's
    ``tracking.position_scale``, the identities' ``jump``): ``setting`` in metres as given, or
    ``auto``: two sides of a voxel of the hull's grid of ``resolution`` voxels per side (a
    fraction of the working volume, whatever the scene's size)."""
    if setting == "auto":
        _, half, _ = working_volume(rig)
        return 2 * (2 * half / int(resolution))
    return float(setting)


def max_tracks(setting: int | str | None, num_windows: int) -> int | None:
    """The export's ``tracking.max_tracks``: ``auto``, the model's ``num_windows`` (no frame
    holds more subjects); a number as given; None, no bound.

    >>> max_tracks("auto", 3), max_tracks(5, 3), max_tracks(None, 3)
    (3, 5, None)
    """
    if setting is None:
        return None
    return int(num_windows) if setting == "auto" else int(setting)


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
    tracklet: int


class SubjectTracker:
    """Link per-frame subjects into tracks (see the module docstring).

    Args:
        appearance_weight: weight of the appearance cosine (the rest goes to box IoU).
        min_similarity: smallest similarity that links a subject to a track.
        max_gap: frames a track may go unseen before it is closed.
        position_weight: share of the similarity given to the positions' closeness when
            both observations have one (0: appearance and boxes only).
        position_scale: distance (world units) at which closeness falls to exp(-1/2).
        max_tracks: most tracks live at once (None: no bound).

    Attributes:
        tracklets: per-frame id -> tracklet id (from 1) of the subjects of the last
            :meth:`update`: a new one where a track opened or was forced on (module
            docstring).

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
        max_tracks: int | None = None,
    ) -> None:
        if not 0.0 <= appearance_weight <= 1.0:
            raise ValueError(f"appearance_weight must be in [0, 1], got {appearance_weight}")
        if not 0.0 <= position_weight <= 1.0 or position_scale <= 0:
            raise ValueError(f"position_weight must be in [0, 1] and position_scale > 0, got "
                             f"{position_weight}, {position_scale}")
        self.appearance_weight = appearance_weight
        self.position_weight, self.position_scale = position_weight, position_scale
        if max_tracks is not None and max_tracks < 1:
            raise ValueError(f"max_tracks must be >= 1 or None, got {max_tracks}")
        self.min_similarity = min_similarity
        self.max_gap = max_gap
        self.max_tracks = max_tracks
        self.tracks: list[_Track] = []
        self.next_id = 1
        self.tracklets: dict[int, int] = {}
        self._next_tracklet = 1

    def update(self, frame: int, subjects: Mapping[int, SubjectObservation]) -> dict[int, int]:
        """Link the subjects of ``frame`` (key: per-frame subject id) to tracks.

        Frames must come in increasing order. Returns per-frame id -> track id.
        """
        self.tracks = [tr for tr in self.tracks if frame - tr.last_frame <= self.max_gap]
        keys = list(subjects)
        out: dict[int, int] = {}
        self.tracklets = {}
        if self.tracks and keys:
            sim = np.array(
                [
                    [track_similarity(tr.last, subjects[k], self.appearance_weight,
                                      self.position_weight, self.position_scale)
                     for k in keys]
                    for tr in self.tracks
                ]
            )
            self._link(frame, subjects, keys, sim, range(len(self.tracks)), self.min_similarity,
                       out)
            if self.max_tracks is not None and len(self.tracks) >= self.max_tracks:
                row = {tr.id: r for r, tr in enumerate(self.tracks)}
                taken = {row[i] for i in out.values()}
                free = [r for r in range(len(self.tracks)) if r not in taken]
                left = [k for k in keys if k not in out]
                if free and left:  # a full house: no new track, the best free one
                    self._link(frame, subjects, left, sim[:, [keys.index(k) for k in left]],
                               free, -np.inf, out, forced=True)
        for k in keys:
            if k not in out:
                self.tracks.append(_Track(self.next_id, subjects[k], frame, self._tracklet()))
                out[k] = self.next_id
                self.tracklets[k] = self.tracks[-1].tracklet
                self.next_id += 1
        return out

    def _tracklet(self) -> int:
        self._next_tracklet += 1
        return self._next_tracklet - 1

    def _link(self, frame: int, subjects: Mapping[int, SubjectObservation], keys: list[int],
              sim: np.ndarray, rows: Sequence[int], floor: float, out: dict[int, int],
              forced: bool = False) -> None:
        """Link ``keys`` to the tracks of ``rows`` by a Hungarian assignment on ``sim``
        (all tracks x ``keys``), pairs below ``floor`` left unlinked; into ``out`` (a
        ``forced`` link starts a tracklet)."""
        rows = list(rows)
        r_idx, c_idx = linear_sum_assignment(-sim[rows])
        for r, c in zip(r_idx, c_idx, strict=True):
            if sim[rows[r], c] >= floor:
                tr, obs = self.tracks[rows[r]], subjects[keys[c]]
                if obs.position is None and tr.last.position is not None:
                    obs = replace(obs, position=tr.last.position)  # seen by one camera
                tr.last, tr.last_frame = obs, frame
                if forced:
                    tr.tracklet = self._tracklet()
                out[keys[c]] = tr.id
                self.tracklets[keys[c]] = tr.tracklet
