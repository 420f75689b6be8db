"""Identities across cameras and time from texture codes (or NSD appearance vectors).

``nsd-export`` gives every subject a track id (``subject_id``: the cross-view
association of a frame, linked over time by box overlap and appearance) and a tracklet id
(``tracklet_id``: the track cut where the tracker opened it or forced a link on it,
:mod:`nsd.inference.tracking`); the steps below that use codes take the tracklets for
tracks (an export without them: the tracks), so that a forced link that joined two
individuals carries no identity across. A track can break (an occlusion, a subject
leaving the view), two tracks can be the same individual, and a track can swap
individuals when they cross. Every
row's identity is therefore decided from its own texture code (NeTePu's
:math:`\\mu` from the visible pixels only, see ``netepu-embed``), in three steps:

1. **Tracks** (:func:`constrained_average_linkage`): each track is described
   by the mean of its rows' unit codes, and tracks are grouped into ``k``
   clusters by average-linkage agglomerative clustering on the cosine
   distance that never joins two tracks seen together in more than
   ``HANDOVER_FRAMES`` frames (so more than ``k`` clusters remain when the
   tracks do not allow fewer).
2. **Rows** (:func:`constrained_kmeans`, ``method="rows"``): a
   spherical k-means over the coded rows in which the rows of one camera-frame
   take distinct identities (a Hungarian assignment per camera-frame on the
   cosine distance to the prototypes); prototypes are the normalised means of
   their rows. It starts from the ``k`` largest clusters' mean unit codes and
   from ``restarts`` sets of ``k`` random rows (seeded), and the run whose rows
   are closest to their prototypes in total is kept. A row whose
   track swapped individuals follows its own code, not its track.
3. **Rows without a code** (keypoints, hence codes, exist on every ``frame_step``-th
   frame only), ``fill="nearest"`` (the default): the identity their track has at its
   nearest coded frame in time (the earlier frame on a tie; a coded frame's identity is the
   most frequent of its rows', smoothed over it and its two neighbouring coded frames), so
   a track that swapped individuals between two coded frames is right up to halfway on
   each side of the swap, and one coded frame with wrong codes changes nothing.
   ``fill="tracks"``: the most frequent identity of all the track's coded rows, wrong
   on the whole stretch after a swap. A tracklet without a coded row takes its track's
   identity the same way, from the track's rows that have one (:func:`_fill_from_tracks`);
   -1 when the whole track has no coded row.

``method="subjects"`` (the default) runs step 2 on *subject-frames* instead of rows: the rows
of one subject in one frame (its cameras, which the export's cross-view association
joined) are one item whose code is the normalised mean of their unit codes, and the
subjects of one frame take distinct identities; every row takes its subject-frame's. A
camera in which the subject is half hidden then no longer decides its row alone. Step 3
decides each tracklet alone, so it can give two subjects of an uncoded frame one identity;
such frames are then made distinct (:func:`distinct_in_frames`: each subject the identity
coded nearest in time on its tracklet, by a Hungarian assignment per frame).
``method="tracks"`` stops after step 1: every row takes its track's cluster.
``method="motion"`` uses no code: every subject-frame takes the trajectory it lies on, the
export's tracks cut where their world positions jump and stitched by position
(:mod:`nsd.inference.stitching`; rows of a subject-frame without a position, seen by one
camera, take their track's identity at its nearest frame with one).
``method="auto"`` (the default) chooses by how well the codes tell the individuals apart
(:func:`code_separation`): ``subjects`` where the two closest subjects of a frame lie at
least ``SEPARATION_MIN`` times farther apart than a subject's codes move over
``SEPARATION_GAP`` frames, ``motion`` otherwise (``tracks`` without positions): individuals
that look alike to the codes, such as mice of one strain, are told apart only by where they
go, and a code-based assignment would be a coin toss in every frame.
``k`` is the number of individuals the export shows at once (the median over
frames of the distinct subjects per frame) unless given. With one subject
(k = 1) no association is needed and every row is identity 0.

Their accuracy against ground truth: :mod:`nsd.evaluation.identity`.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from nsd.inference.stitching import motion_identities
from nsd.ops.vectors import unit_vectors

__all__ = [
    "FILL_METHODS",
    "HANDOVER_FRAMES",
    "IDENTITY_METHODS",
    "SEPARATION_GAP",
    "SEPARATION_MIN",
    "assign_identities",
    "auto_method",
    "code_separation",
    "constrained_average_linkage",
    "constrained_kmeans",
    "distinct_in_frames",
    "majority_in_window",
    "nearest_in_time",
    "row_groups",
    "subject_frames",
    "transfer_identities",
]

IDENTITY_METHODS = ("auto", "subjects", "rows", "tracks", "motion")
Positions = Mapping[tuple[int, int], np.ndarray]  # (frame, subject_id) -> world position (3,)
# method="auto": the codes tell individuals apart when code_separation is at least this.
# Measured on the contact scenes' 15-minute runs (docs/benchmarks/code_separation.md):
# 4.7-47 with distinct textures (6.5-6.7 for the pool's look-alike pair), 0.75-0.82 with one
# texture for all three individuals of the huddle it was chosen on; 0.52-1.12 on four groups
# of one texture made after (3-4 bipeds, 2-3 quadrupeds).
SEPARATION_MIN = 2.0
# ... comparing a track's codes this many frames apart (the keypoints stage's default
# frame_step): codes of every frame would move little from one to the next whoever they are.
SEPARATION_GAP = 25
FILL_METHODS = ("nearest", "tracks")  # rows without a code; "app" is transfer_identities
# distinct_in_frames: a track's coded frame counts as this many frames farther than one of
# the subject's own tracklet (the tracklet vouches for its individual, the track may not)
TRACK_SUPPORT_FRAMES = 1000
_NO_SUPPORT = 1e9  # no coded frame of that identity on the tracklet or the track
# Two tracks seen together in at most this many frames may still be one individual: the
# tracker may open a track for an individual a few frames before it closes the old one (a
# handover). Measured on the contact runs (docs/pipeline.md "Individuals that look alike"):
# with 0, four 15-minute runs kept a fourth identity for three individuals; 3, 5 and 10
# gave the same identities.
HANDOVER_FRAMES = 5


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


def constrained_kmeans(
    codes: np.ndarray, groups: np.ndarray, prototypes: np.ndarray, max_iter: int = 100
) -> np.ndarray:
    """Spherical k-means in which the rows of one group take distinct clusters.

    Each iteration assigns every group's rows to the prototypes by a Hungarian
    assignment on the cosine distance (rows beyond the k of a group, if any,
    take their nearest prototype), then sets each prototype to the normalised
    mean of its rows (a prototype without rows stays). It stops when no label
    changes; the assignment cost never increases.

    Args:
        codes: (R, D) row codes (normalised here).
        groups: (R,) int, rows of one group (a camera-frame) are kept apart.
        prototypes: (k, D) starting prototypes.
        max_iter: iteration cap.

    Returns:
        ``(labels (R,) in [0, k), cost)``: the total cosine distance of the rows to
        their prototypes.
    """

    u = unit_vectors(np.asarray(codes, np.float64), eps=1e-12)
    proto = unit_vectors(np.asarray(prototypes, np.float64), eps=1e-12)
    members = [np.flatnonzero(groups == g) for g in np.unique(groups)]
    labels = np.full(len(u), -1, np.int64)
    for _ in range(max_iter):
        new = np.empty_like(labels)
        for rows in members:
            cost = 1 - u[rows] @ proto.T
            r, c = linear_sum_assignment(cost)
            new[rows] = cost.argmin(1)
            new[rows[r]] = c
        if np.array_equal(new, labels):
            break
        labels = new
        proto = np.stack(
            [
                unit_vectors(u[labels == j].mean(0), eps=1e-12) if (labels == j).any() else proto[j]
                for j in range(len(proto))
            ]
        )
    return labels, float((1 - (u * proto[labels]).sum(1)).sum())


def assign_identities(
    table: dict[str, np.ndarray],
    column: str = "texture",
    k: int = 0,
    method: str = "auto",
    restarts: int = 10,
    fill: str = "nearest",
    positions: Positions | Callable[[], Positions] | None = None,
    jump: float = 0.0,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Identity of every row of an export's embedding table.

    Args:
        table: columns ``subject_id``, ``frame`` and ``column`` (rows, D), optionally
            ``<column>_valid`` and ``tracklet_id`` (the export's: then the code-based
            methods take the tracklets for tracks); ``method="rows"`` also needs ``camera``.
        column: the texture-code column.
        k: identities (0: the median number of subjects per frame).
        method: ``subjects`` (each subject-frame by its rows' pooled code), ``rows`` (each
            coded row by its own code), ``tracks`` (each row its track's cluster), ``motion``
            (each subject-frame its trajectory, by position) or ``auto`` (``subjects`` where
            the codes tell the individuals apart, else ``motion``, or ``tracks`` without
            ``positions``); see the module.
        restarts: ``subjects``, ``rows``: k-means runs from ``k`` random rows (seeded) besides the
            one from the track clusters; the run of least cost is kept.
        fill: ``subjects``, ``rows``: how rows without a code get an identity from the coded rows of
            their track, one of :data:`FILL_METHODS` (see the module).
        positions: ``motion``: (frame, subject_id) -> world position (3,) of the
            subject-frames seen by two or more cameras, or a function that gives them
            (called only where ``motion`` is taken: they cost a decode of every mask).
        jump: ``motion``: longest step of a track between two frames (world units) before it
            is cut (:func:`nsd.inference.stitching.cut_tracklets`).

    Returns:
        ``(identity (rows,) int64, summary)``; -1 for rows of tracks without a valid code
        (``motion``: without a position).
        With ``auto``, ``summary["method"]`` is the method chosen and
        ``summary["separation"]`` the :func:`code_separation` it was chosen by.

    Raises:
        ValueError: an unknown ``method`` or ``fill``; ``motion`` without ``positions`` or
            ``jump``.
    """
    if method not in IDENTITY_METHODS:
        raise ValueError(f"identities: method must be one of {IDENTITY_METHODS}, got {method!r}")
    if fill not in FILL_METHODS:
        raise ValueError(f"identities: fill must be one of {FILL_METHODS}, got {fill!r}")
    if method == "motion":
        positions = _resolved(positions)
        if not positions or not jump > 0:
            raise ValueError("identities: method motion needs the subjects' world positions "
                             f"and a jump > 0 (got jump={jump})")
    subject = np.asarray(table["subject_id"], np.int64)
    sid = np.asarray(table["tracklet_id"], np.int64) if "tracklet_id" in table else subject
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
    identity = np.full(len(sid), -1, np.int64)
    summary: dict[str, Any] = {"tracks": len(tracks), "k": k, "method": method}
    if method == "motion":
        identity, part = _by_motion(subject, frame, k, positions, jump)
        return identity, summary | part
    if not tracks:
        return identity, summary | {"identities": 0, "association": "no texture codes"}
    coded = np.isin(sid, tracks)
    if k == 1 or len(tracks) == 1:
        identity[coded] = 0
        if sid is not subject:
            _fill_from_tracks(identity, subject, frame, fill)
        return identity, summary | {"identities": 1, "association": "skipped: one subject"}
    unit = unit_vectors(codes[valid], eps=1e-12)
    if method in ("auto", "subjects"):
        items, item, pooled = subject_frames(unit, frame[valid], sid[valid])
    if method == "auto":
        separation = code_separation(pooled, items[:, 0], items[:, 1])
        method = auto_method(separation, positions is not None and jump > 0)
        if method == "motion":
            positions = _resolved(positions)
            method = "motion" if positions else "tracks"  # nobody seen by two cameras
        summary |= {"method": method, "chosen_by": "auto", "separation": separation}
        if method == "motion":
            identity, part = _by_motion(subject, frame, k, positions, jump)
            return identity, summary | part
    of_track, n_clusters = _cluster_tracks(unit, sid[valid], tracks, per_frame, k)
    if method == "tracks":
        identity[coded] = [of_track[int(s)] for s in sid[coded]]
        if sid is not subject:
            _fill_from_tracks(identity, subject, frame, fill)
        return identity, summary | {
            "identities": n_clusters,
            "association": f"tracks clustered by {column}",
        }
    if method == "subjects":  # one item per subject and frame, distinct within a frame
        labels = _cluster_rows(pooled, np.array([of_track[int(t)] for t in items[:, 1]]),
                               items[:, 0], k, restarts)
        identity[valid] = labels[item]
    else:
        row_track = np.array([of_track[int(s)] for s in sid[valid]])
        cams = np.unique(np.asarray(table["camera"])[valid], return_inverse=True)[1]
        groups = frame[valid] * (cams.max() + 1) + cams
        identity[valid] = _cluster_rows(unit, row_track, groups, k, restarts)
    coded_tracks = set(tracks)
    for s, rows in row_groups(sid):  # uncoded rows of a coded track
        if s not in coded_tracks:
            continue
        gap, known = rows[~valid[rows]], rows[valid[rows]]
        if not len(gap):
            continue
        if fill == "tracks":  # the track's most frequent identity
            identity[gap] = _most_frequent(identity[known])
        else:
            identity[gap] = _nearest_coded(frame[known], identity[known], frame[gap])
    if sid is not subject:  # tracklets without a code: their track's, as ``fill`` says
        _fill_from_tracks(identity, subject, frame, fill)
    if method == "subjects":
        summary["frames_made_distinct"] = distinct_in_frames(identity, frame, subject, sid,
                                                             valid, k)
    return identity, summary | {
        "identities": len(set(identity[valid].tolist())),
        "association": f"{method} clustered by {column}",
    }


def subject_frames(unit: np.ndarray, frame: np.ndarray, subject: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The subject-frames of R coded rows (unit codes (R, D), ``frame`` and ``subject``
    (R,)): ``(items (S, 2) [frame, subject], item (R,) each row's subject-frame, pooled
    (S, D) the normalised mean unit code of each subject-frame's rows)``."""
    items, item = np.unique(np.stack([frame, subject], 1), axis=0, return_inverse=True)
    item = item.reshape(-1)
    pooled = np.zeros((len(items), unit.shape[1]))
    np.add.at(pooled, item, unit)
    return items, item, unit_vectors(pooled, eps=1e-12)


def auto_method(separation: float, motion: bool = True) -> str:
    """The method ``auto`` takes for codes of this :func:`code_separation`: ``subjects`` from
    ``SEPARATION_MIN`` up, else ``motion`` (``tracks`` where there are no positions, not
    ``motion``)."""
    if separation >= SEPARATION_MIN:
        return "subjects"
    return "motion" if motion else "tracks"


def _resolved(positions: Positions | Callable[[], Positions] | None) -> Positions | None:
    """``positions`` as given, or what the function given returns (called here, once)."""
    return positions() if callable(positions) else positions


def _by_motion(sid: np.ndarray, frame: np.ndarray, k: int, positions: Positions, jump: float
               ) -> tuple[np.ndarray, dict[str, Any]]:
    """``method="motion"``: (rows,) identities of rows of ``sid``, ``frame`` (rows,) and the
    summary's part: each subject-frame its trajectory
    (:func:`nsd.inference.stitching.motion_identities`), rows of a subject-frame without a
    position their track's identity at its nearest frame with one (-1: none, counted in
    ``rows_without_position``)."""
    keys = set(zip(frame.tolist(), sid.tolist(), strict=True))
    label, pieces = motion_identities(
        {key: p for key, p in positions.items() if key in keys}, k, jump,
        handover=HANDOVER_FRAMES) if k > 1 else ({key: 0 for key in keys if key in positions}, 0)
    identity = np.array([label.get(key, -1) for key in zip(frame.tolist(), sid.tolist(),
                                                             strict=True)], np.int64)
    for s in np.unique(sid[identity < 0]):
        rows = sid == s
        known = rows & (identity >= 0)
        if known.any():
            gap = rows & (identity < 0)
            order = np.argsort(frame[known], kind="stable")
            times, ids = frame[known][order], identity[known][order]
            identity[gap] = ids[nearest_in_time(times, frame[gap])]
    return identity, {"identities": len(set(identity[identity >= 0].tolist())),
                      "association": f"motion: {pieces} tracklets stitched by position",
                      "tracklets": pieces, "rows_without_position": int((identity < 0).sum())}


def code_separation(codes: np.ndarray, frame: np.ndarray, track: np.ndarray,
                    gap: int = SEPARATION_GAP) -> float:
    """How well texture codes tell individuals apart: the median over frames of the cosine
    distance between the two closest subjects of a frame, over the median cosine distance
    between one track's code at a frame and at its first coded frame ``gap`` or more frames
    later (what a code moves with pose and view; coded frames every ``frame_step`` = 25
    frames, the keypoints stage's default, make these the consecutive ones). About 1 or
    less: the codes do not tell the individuals apart.

    Args:
        codes: (S, D) unit codes of S subject-frames.
        frame, track: (S,) each subject-frame's frame and track id.
        gap: frames between the two codes of a track that are compared.

    Returns:
        the ratio; ``inf`` where there is nothing to compare (no frame of two subjects, or
        no track coded twice ``gap`` frames apart), 0 where the closest subjects' codes are
        equal.

    Example:
        >>> a, b = np.eye(2)
        >>> codes = np.stack([a, b, 0.8 * a + 0.6 * b, b])  # frames 0 and 25, tracks 1 and 2
        >>> round(code_separation(codes, np.array([0, 0, 25, 25]), np.array([1, 2, 1, 2])), 6)
        7.0
    """
    closest = []
    for f in np.unique(frame):
        u = codes[frame == f]
        if len(u) > 1:
            d = 1 - u @ u.T
            closest.append(float(d[np.triu_indices(len(u), 1)].min()))
    moved = []
    for t in np.unique(track):
        order = np.argsort(frame[track == t], kind="stable")
        f, u = frame[track == t][order], codes[track == t][order]
        later = np.searchsorted(f, f + gap)  # each code's first partner gap frames on
        ok = later < len(f)
        moved += (1 - (u[ok] * u[later[ok]]).sum(1)).tolist()
    if not closest or not moved:
        return float("inf")
    between, within = float(np.median(closest)), float(np.median(moved))
    if between <= 1e-9:  # cosine distances this small are rounding: equal codes
        return 0.0
    return between / within if within > 1e-9 else float("inf")


def _most_frequent(ids: np.ndarray) -> int:
    """The most frequent value of ``ids`` (the smallest on a tie)."""
    values, counts = np.unique(ids, return_counts=True)
    return int(values[counts.argmax()])


def distinct_in_frames(identity: np.ndarray, frame: np.ndarray, subject: np.ndarray,
                       piece: np.ndarray, coded: np.ndarray, k: int) -> int:
    """Give the subjects of each frame distinct identities where the fill gave two of them
    one (in place; rows (R,) of ``identity``, ``frame``, ``subject`` the export's track and
    ``piece`` its tracklet, ``coded`` the rows with a code). The fill decides each tracklet
    alone, so where a track's swap falls between two coded frames, two subjects of a frame
    can take one identity, and one of them is wrong. In such a frame the subjects take the
    ``k`` identities by a Hungarian assignment on how far in time each subject's tracklet
    has a coded frame of each identity (its track's, ``TRACK_SUPPORT_FRAMES`` further,
    where the tracklet has none; a coded subject-frame is at distance 0 from its own). A
    subject-frame is one item: all its rows move together. Returns the frames changed.
    """
    if k < 2:
        return 0
    sf, sf_of_row = np.unique(np.stack([frame, subject], 1), axis=0, return_inverse=True)
    sf_of_row = sf_of_row.reshape(-1)
    current = np.full(len(sf), -1, np.int64)
    current[sf_of_row] = identity  # a subject-frame's rows share one identity
    sf_piece = np.zeros(len(sf), np.int64)
    sf_piece[sf_of_row] = piece
    is_coded = np.zeros(len(sf), bool)
    np.logical_or.at(is_coded, sf_of_row, coded)
    known = current >= 0
    pairs, counts = np.unique(np.stack([sf[known, 0], current[known]], 1), axis=0,
                              return_counts=True)
    dup_frames = np.unique(pairs[counts > 1, 0])
    if not len(dup_frames):
        return 0
    support = _support(sf[is_coded, 0], sf_piece[is_coded], current[is_coded])
    track_support = _support(sf[is_coded, 0], sf[is_coded, 1], current[is_coded])
    by_sf = np.argsort(sf_of_row, kind="stable")  # the rows of subject-frame j:
    first = np.searchsorted(sf_of_row[by_sf], np.arange(len(sf) + 1))  # by_sf[first[j]:...]
    changed = 0
    for t in dup_frames.tolist():
        items = np.arange(*np.searchsorted(sf[:, 0], [t, t + 1]))  # sf is sorted by frame
        cost = np.array([[_distance(support, sf_piece[j], i, t, track_support, sf[j, 1])
                          for i in range(k)] for j in items])
        moved = False
        for r, c in zip(*linear_sum_assignment(cost), strict=True):
            if current[items[r]] != c:
                identity[by_sf[first[items[r]]:first[items[r] + 1]]] = c
                moved = True
        changed += moved
    return changed


def _support(frames: np.ndarray, owner: np.ndarray, ids: np.ndarray
             ) -> dict[tuple[int, int], np.ndarray]:
    """(owner, identity) -> the sorted frames of the owner's coded subject-frames of it."""
    out: dict[tuple[int, int], list] = defaultdict(list)
    for t, o, i in zip(frames.tolist(), owner.tolist(), ids.tolist(), strict=True):
        out[(o, i)].append(t)
    return {key: np.sort(np.asarray(v)) for key, v in out.items()}


def _distance(support: dict, piece: int, i: int, t: int, track_support: dict,
              track: int) -> float:
    """Frames from ``t`` to the nearest coded frame of identity ``i`` on the tracklet, else
    on the track (+ ``TRACK_SUPPORT_FRAMES``), else a very large number."""
    for table, key, extra in ((support, piece, 0), (track_support, track,
                                                     TRACK_SUPPORT_FRAMES)):
        frames = table.get((key, i))
        if frames is not None:
            return float(np.abs(frames - t).min() + extra)
    return _NO_SUPPORT


def row_groups(owner: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """``(owner, its row indices in order)`` for every value of ``owner`` (rows,): one sort,
    not a scan of all rows per owner (a long recording has thousands of tracklets).

    >>> [(o, r.tolist()) for o, r in row_groups(np.array([3, 1, 3, 2]))]
    [(1, [1]), (2, [3]), (3, [0, 2])]
    """
    order = np.argsort(owner, kind="stable")
    values, first = np.unique(owner[order], return_index=True)
    return list(zip(values.tolist(), np.split(order, first[1:]), strict=True))


def _fill_from_tracks(identity: np.ndarray, track: np.ndarray, frame: np.ndarray,
                      fill: str) -> None:
    """Rows of a tracklet without a coded row (-1) take, in place, the identity their track
    (``track`` (rows,), the export's ``subject_id``) has among its rows that have one: at the
    nearest frame in time (``fill="nearest"``) or the most frequent (``"tracks"``). Where the
    tracker forced links often (real footage whose boxes jump, docs/pipeline.md "At most as
    many tracks as windows"), most tracklets hold no coded frame; the track's forced links
    are right more often than not, and an identity is better than none."""
    missing = set(np.unique(track[identity < 0]).tolist())
    for s, rows in row_groups(track):
        if s not in missing:
            continue
        known, gap = rows[identity[rows] >= 0], rows[identity[rows] < 0]
        if not len(known):
            continue
        if fill == "tracks":
            identity[gap] = _most_frequent(identity[known])
        else:
            identity[gap] = _nearest_coded(frame[known], identity[known], frame[gap])


def _nearest_coded(coded_frame: np.ndarray, coded_id: np.ndarray, frames: np.ndarray
                   ) -> np.ndarray:
    """For each of ``frames`` (G,), the identity of the nearest coded frame in time (the
    earlier frame on a tie), from one track's coded rows (``coded_frame``, ``coded_id``
    (C,)). A coded frame's identity is the most frequent of its rows', then the most
    frequent of it and its two neighbouring coded frames (its own on a tie): one coded frame
    whose codes were wrong does not flip the rows around it, a swap that lasts two coded
    frames does. Returns (G,) int64."""
    times = np.unique(coded_frame)
    own = [_most_frequent(coded_id[coded_frame == t]) for t in times]
    ids = np.array(majority_in_window(own, 1))
    return ids[nearest_in_time(times, frames)]


def majority_in_window(labels: list, window: int) -> list:
    """Each of ``labels`` (in time order) replaced by the most frequent label of it and its
    ``window`` neighbours on either side; its own wins a tie it is in, otherwise the
    smallest of the tied. One odd label among its neighbours is outvoted, a change that
    lasts longer than the window is followed.

    Example:
        >>> majority_in_window([0, 0, 1, 0, 1, 1, 1], 1)
        [0, 0, 0, 1, 1, 1, 1]
    """
    out = list(labels)
    for i, own in enumerate(labels):
        votes = Counter(labels[max(0, i - window): i + window + 1])
        best = max(votes.values())
        if votes[own] < best:
            out[i] = min(v for v, n in votes.items() if n == best)
    return out


def nearest_in_time(times: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """For each of ``frames`` (G,), the index of the nearest of the sorted ``times`` (T,)
    (the earlier on a tie). Returns (G,) int64.

    Example:
        >>> nearest_in_time(np.array([0, 10, 20]), np.array([4, 5, 6, 30])).tolist()
        [0, 0, 1, 2]
    """
    frames = np.asarray(frames)
    after = np.clip(np.searchsorted(times, frames), 0, len(times) - 1)
    before = np.clip(after - 1, 0, len(times) - 1)
    take_before = np.abs(frames - times[before]) <= np.abs(times[after] - frames)
    return np.where(take_before, before, after)


def transfer_identities(
    table: dict[str, np.ndarray], identity: np.ndarray, coded: np.ndarray, column: str = "app"
) -> np.ndarray:
    """Carry the identities of the ``coded`` rows to the others through a second embedding
    that every row has (NSD's appearance vectors ``app``): each identity's prototype is the
    normalised mean unit ``column`` vector of its coded rows, and the other rows of each
    camera-frame take distinct identities by a Hungarian assignment on the cosine distance
    (rows beyond the number of identities take their nearest).

    Texture codes need keypoints, which the pipeline inverts on every 25th frame only; the
    tracks between coded frames can swap individuals, so a track's identity is no way to
    fill the gaps (``assign_identities``' own fill), an appearance vector of the row is.

    Args:
        table: columns ``camera``, ``frame`` and ``column`` (rows, D).
        identity: (rows,) from the codes; entries of rows not ``coded`` are replaced.
        coded: (rows,) bool, the rows whose identity comes from their own code.

    Returns:
        (rows,) int64.
    """
    out = np.asarray(identity, np.int64).copy()
    ids = sorted({int(i) for i in out[coded] if i >= 0})
    if not ids:
        return out
    unit = unit_vectors(np.asarray(table[column], np.float64), eps=1e-12)
    proto = np.stack([unit_vectors(unit[coded & (out == i)].mean(0), eps=1e-12) for i in ids])
    cost = 1 - unit @ proto.T  # (rows, identities)
    groups: dict[tuple[str, int], list[int]] = defaultdict(list)
    for r in np.flatnonzero(~coded):
        groups[(str(table["camera"][r]), int(table["frame"][r]))].append(int(r))
    for rows in groups.values():
        c = cost[rows]
        picked, taken = linear_sum_assignment(c)
        for a, b in zip(picked.tolist(), taken.tolist(), strict=True):
            out[rows[a]] = ids[b]
        for a in sorted(set(range(len(rows))) - set(picked.tolist())):
            out[rows[a]] = ids[int(np.argmin(c[a]))]
    return out


def _cluster_tracks(
    unit: np.ndarray, row_sid: np.ndarray, tracks: list[int], per_frame: dict, k: int
) -> tuple[dict[int, int], int]:
    """Step 1: tracks grouped into ``k`` clusters by their mean unit code, never joining
    two tracks seen together in more than ``HANDOVER_FRAMES`` frames; returns track ->
    cluster and the number of clusters."""
    desc = np.stack([unit_vectors(unit[row_sid == s].mean(0), eps=1e-12) for s in tracks])
    dist = np.clip(1 - desc @ desc.T, 0, 2)
    index = {s: i for i, s in enumerate(tracks)}
    together = np.zeros(dist.shape, np.int64)  # frames in which both tracks are seen
    for members in per_frame.values():
        m = [index[s] for s in members if s in index]
        together[np.ix_(m, m)] += 1
    apart = together > HANDOVER_FRAMES
    np.fill_diagonal(apart, False)
    track_label = constrained_average_linkage(dist, apart, k)
    return {s: int(track_label[i]) for s, i in index.items()}, len(set(track_label.tolist()))


def _cluster_rows(
    unit: np.ndarray, row_track: np.ndarray, groups: np.ndarray, k: int, restarts: int
) -> np.ndarray:
    """Step 2: constrained k-means over the coded rows from the ``k`` largest track
    clusters and from ``restarts`` random starts (seed 0); the run of least cost."""
    sizes = np.bincount(row_track)
    start = np.argsort(-sizes, kind="stable")[:k]
    proto = np.stack([unit_vectors(unit[row_track == j].mean(0), eps=1e-12) for j in start])
    rng = np.random.default_rng(0)
    starts = [proto] + [
        unit[rng.choice(len(unit), k, replace=False)] for _ in range(restarts) if len(unit) >= k
    ]
    runs = [constrained_kmeans(unit, groups, p) for p in starts]
    return min(runs, key=lambda r: r[1])[0]


