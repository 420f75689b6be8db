"""Identities from where the subjects go: tracks cut where they jump, stitched by position.

Individuals that look alike (one strain, one colour) are told apart only by where they go.
The per-frame tracker (:class:`nsd.inference.tracking.SubjectTracker`) describes a track by
its last observation, so one frame whose decomposition mixes two bodies (a window spanning
two, its position between them) moves every track of the huddle onto a neighbour's body,
and the swap is kept for the rest of the sequence. With the whole sequence at hand, the
subject-frames' world positions (:func:`nsd.export.positions.triangulate_positions`) are
linked again, in three steps:

1. **Cut** (:func:`cut_tracklets`): each track's positions in time order are cut wherever
   one step is longer than ``jump * sqrt(gap)``, ``gap`` the frames between the two
   positions: a body moves little from one frame to the next, a track that moved onto
   another body jumps by about the distance between the two.
2. **Stitch** (:func:`stitch_tracklets`): the pieces (tracklets) of at least
   ``min_length`` subject-frames, in order of their first frame, take one of ``k``
   trajectories. The tracklets that start in one frame are matched to the trajectories free
   there (their last tracklet ended before that frame, or at most ``handover`` frames into
   it) by a Hungarian assignment on the distance from the trajectory's last position to the
   tracklet's first; a tracklet left over opens a trajectory while there are fewer than
   ``k``, else takes the nearest (two trajectories then share that stretch).
3. **Short pieces** (fewer than ``min_length`` subject-frames: most are the mixed frames
   themselves): the subject-frames of each frame are matched by a Hungarian assignment to
   the trajectories no long tracklet holds in that frame, on the distance to each
   trajectory's position at its nearest frame in time; any beyond those take the nearest.

No appearance is used: where codes tell individuals apart, they decide
(:mod:`netepu.reid.identities`); this is for where they do not. The assignments are scipy's
Hungarian (``linear_sum_assignment``). A min-cost flow over all subject-frames (networkx's
``min_cost_flow``, the classical global tracker) would also choose how many trajectories
there are; here that number is known (``k``), and the greedy stitch in time order reached
identity 0.994-0.998 on the look-alike scenes (docs/pipeline.md "Individuals that look
alike"), so it was not needed.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from itertools import pairwise

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["MIN_TRACKLET", "cut_tracklets", "motion_identities", "stitch_tracklets"]

# Tracklets shorter than this are placed frame by frame (step 3), not stitched. On the
# one-texture huddle (docs/pipeline.md "Individuals that look alike"), 3 and 5 gave the
# same identities.
MIN_TRACKLET = 3

Key = tuple[int, int]  # (frame, track)


def cut_tracklets(positions: Mapping[Key, np.ndarray], jump: float) -> list[list[Key]]:
    """The tracks of ``positions`` ((frame, track) -> world position (3,)) cut where they jump.

    Args:
        positions: each subject-frame's position.
        jump: longest step (world units) between consecutive frames of one tracklet; over a
            gap of ``g`` frames, ``jump * sqrt(g)``.

    Returns:
        the tracklets, each its keys in time order.

    Example:
        >>> p = {(0, 1): np.zeros(3), (1, 1): np.full(3, 0.1), (2, 1): np.full(3, 2.0)}
        >>> cut_tracklets(p, 0.5)
        [[(0, 1), (1, 1)], [(2, 1)]]
    """
    if not jump > 0:
        raise ValueError(f"jump must be > 0, got {jump}")
    frames: dict[int, list[int]] = defaultdict(list)
    for f, s in positions:
        frames[int(s)].append(int(f))
    out = []
    for s in sorted(frames):
        fs = sorted(frames[s])
        piece = [(fs[0], s)]
        for a, b in pairwise(fs):
            step = float(np.linalg.norm(np.asarray(positions[(b, s)]) -
                                        np.asarray(positions[(a, s)])))
            if step > jump * np.sqrt(b - a):
                out.append(piece)
                piece = []
            piece.append((b, s))
        out.append(piece)
    return out


def stitch_tracklets(
    positions: Mapping[Key, np.ndarray], tracklets: list[list[Key]], k: int,
    min_length: int = MIN_TRACKLET, handover: int = 0,
) -> dict[Key, int]:
    """Steps 2 and 3 of the module: every subject-frame of ``tracklets`` -> a trajectory in
    [0, k).

    Args:
        positions: (frame, track) -> world position (3,) of every key of ``tracklets``.
        tracklets: from :func:`cut_tracklets`.
        k: trajectories (individuals), >= 1.
        min_length: shorter tracklets are placed frame by frame.
        handover: a trajectory is free for a tracklet that starts at most this many frames
            before its last tracklet ends.

    Returns:
        (frame, track) -> trajectory.

    Example (two bodies 1 apart; track 1 jumps onto the other body at frame 3, track 2 too):
        >>> a, b = np.zeros(3), np.array([1.0, 0, 0])
        >>> p = {(f, 1): (a if f < 3 else b) for f in range(6)}
        >>> p |= {(f, 2): (b if f < 3 else a) for f in range(6)}
        >>> lab = stitch_tracklets(p, cut_tracklets(p, 0.5), 2)
        >>> [lab[(f, 1)] for f in range(6)], [lab[(f, 2)] for f in range(6)]
        ([0, 0, 0, 1, 1, 1], [1, 1, 1, 0, 0, 0])
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    pos = {key: np.asarray(p, np.float64) for key, p in positions.items()}
    long = sorted((t for t in tracklets if len(t) >= min_length), key=lambda t: t[0][0])
    ends: list[int] = []  # per trajectory, the last frame of its tracklets
    last: list[np.ndarray] = []  # ... and the position there
    label: dict[Key, int] = {}
    i = 0
    while i < len(long):
        start = long[i][0][0]
        group = []
        while i < len(long) and long[i][0][0] == start:
            group.append(long[i])
            i += 1
        free = [j for j, end in enumerate(ends) if end < start + handover]
        cost = np.array([[np.linalg.norm(last[j] - pos[t[0]]) for j in free] for t in group])
        got = dict(zip(*linear_sum_assignment(cost.reshape(len(group), len(free))),
                       strict=True)) if free else {}
        for g, t in enumerate(group):
            if g in got:
                j = free[got[g]]
            elif len(ends) < k:
                ends.append(-1)
                last.append(pos[t[0]])
                j = len(ends) - 1
            else:
                j = int(np.argmin([np.linalg.norm(q - pos[t[0]]) for q in last]))
            if t[-1][0] >= ends[j]:
                ends[j], last[j] = t[-1][0], pos[t[-1]]
            label.update(dict.fromkeys(t, j))
    _place_short([key for t in tracklets if len(t) < min_length for key in t], pos, label, k)
    return label


def _place_short(keys: list[Key], pos: dict[Key, np.ndarray], label: dict[Key, int],
                 k: int) -> None:
    """Step 3: the subject-frames ``keys`` of short tracklets into ``label`` (which holds the
    long ones'; with none, each frame's keys take 0, 1, ... in track order, at most k - 1)."""
    traj: dict[int, dict[int, np.ndarray]] = defaultdict(dict)
    taken: dict[int, set[int]] = defaultdict(set)
    for (f, s), j in label.items():
        traj[j][f] = pos[(f, s)]
        taken[f].add(j)
    times = {j: np.array(sorted(traj[j])) for j in traj}
    by_frame: dict[int, list[Key]] = defaultdict(list)
    for key in keys:
        by_frame[key[0]].append(key)
    for f, ks in by_frame.items():
        ks = sorted(ks)
        if not times:
            label.update({key: min(m, k - 1) for m, key in enumerate(ks)})
            continue
        js = sorted(times)
        at = {j: traj[j][_nearest(times[j], f)] for j in js}
        cost = np.array([[np.linalg.norm(at[j] - pos[key]) for j in js] for key in ks])
        free = [c for c, j in enumerate(js) if j not in taken[f]]
        rows, cols = linear_sum_assignment(cost[:, free]) if free else ([], [])
        for r, c in zip(rows, cols, strict=True):
            label[ks[r]] = js[free[c]]
        for r in set(range(len(ks))) - set(np.asarray(rows).tolist()):
            label[ks[r]] = js[int(np.argmin(cost[r]))]


def _nearest(times: np.ndarray, frame: int) -> int:
    """The one of the sorted ``times`` (T,) nearest to ``frame`` (the earlier on a tie), in
    O(log T): a long recording holds tens of thousands of frames per trajectory.

    Example:
        >>> [_nearest(np.array([0, 10, 20]), f) for f in (-5, 5, 6, 30)]
        [0, 0, 10, 20]
    """
    after = min(int(np.searchsorted(times, frame)), len(times) - 1)
    before = max(after - 1, 0)
    near = before if abs(frame - times[before]) <= abs(times[after] - frame) else after
    return int(times[near])


def motion_identities(
    positions: Mapping[Key, np.ndarray], k: int, jump: float,
    min_length: int = MIN_TRACKLET, handover: int = 0,
) -> tuple[dict[Key, int], int]:
    """The module's three steps: (frame, track) -> identity in [0, k), and the number of
    tracklets the tracks were cut into."""
    pieces = cut_tracklets(positions, jump)
    return stitch_tracklets(positions, pieces, k, min_length, handover), len(pieces)
