r"""Front and back from the subject's own track: a fit turned against its neighbours is refitted.

Silhouettes hardly tell a body from the same body turned front to back, and where a view's
mask is poor the inversion can settle on a body turned half round (a quadruped with its head
where its tail is: 0.8-1.5 m of MPJPE, the tail of the three cows of one texture in
docs/benchmarks/keypoints_heading.md). For bipeds the direction of travel relabels left for
right (:mod:`netepu.pipeline.travel`); a quadruped turned round is not a relabelling, and
its travel faced its left-right axis in only 75-91 % of its fast frames. What does hold is
that a body turns little between two fitted frames of its track, so the fits of a subject's
neighbouring frames say which way it faces.

The heading of a pose :math:`p` (K, 3): the turn about the up axis :math:`u` that best aligns
the species' rest pose :math:`r` (body frame: x forward, z up;
:attr:`nsd.synth.skeleton.Species.rest`) with it on the ground plane (2D Procrustes),

.. math::
    \theta = \operatorname{atan2}\Big(\sum_k r_{k,x}\, q_{k,2} - r_{k,y}\, q_{k,1},\;
    \sum_k r_{k,x}\, q_{k,1} + r_{k,y}\, q_{k,2}\Big),

with :math:`q_k` the centred pose in the ground-plane axes :math:`(e_1, e_2)` of
:func:`nsd.ops.vectors.up_frame` and :math:`r` centred (:func:`heading`). A whole body
decides it, not two keypoints.

The heading expected at a subject-frame is the short-arc midpoint of the fits of the same
subject at the fitted frames just before and after it (at the ends of a track, the one
neighbour's); neighbours that face nearly opposite ways (more than :data:`AMBIGUOUS` apart)
expect nothing, and neither do neighbours more than :data:`NEIGHBOUR_SECONDS` away: the
synthetic cows turn up to ~90 degrees in 0.4 s, and half round within a second, so fits a
second apart (``nsd-run``'s every 25th frame at 25 frames/s) say nothing of each other's
heading (docs/netepu.md "Front and back from the track"). A fit more than ``max_turn``
(90 degrees) from what is expected is refitted from its own pose turned to the expected
heading (:func:`turned_pose`), and the refit
replaces the first when its silhouette loss is at most ``tolerance`` times the first's
(:func:`netepu.pipeline.subject_keypoints.invert_export`): the track only proposes, the
masks decide.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence

import numpy as np
import torch

from netepu.geometry.inverse import rotate_about_up
from nsd.ops.vectors import up_frame, wrap_angle

__all__ = ["AMBIGUOUS", "MAX_TURN", "NEIGHBOUR_SECONDS", "expected_headings", "heading",
           "turned_pose", "turns"]

MAX_TURN = math.radians(90)  # a fit this far from its neighbours' heading is refitted
AMBIGUOUS = math.radians(170)  # neighbours this far apart expect no heading
NEIGHBOUR_SECONDS = 0.5  # neighbours further apart in time expect no heading


def heading(keypoints: np.ndarray, rest: np.ndarray, up: Sequence[float]) -> float:
    """The module docstring's :math:`\\theta` of a pose, radians from :math:`e_1` towards
    :math:`e_2`.

    Shape:
        keypoints (K, 3) world; rest (K, 3) the species' body frame (x forward, z up).

    Example:
        >>> rest = np.array([[1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [0.0, 0.3, 1.0]])
        >>> pose = rest[:, [1, 0, 2]] * [-1, 1, 1]  # turned a quarter turn: x forward -> y
        >>> round(math.degrees(heading(pose, rest, (0.0, 0.0, 1.0))))
        90
    """
    basis = up_frame(torch.tensor(up, dtype=torch.float64)).numpy()
    p = np.asarray(keypoints, np.float64)
    q = (p - p.mean(0)) @ basis[:, :2]  # (K, 2): e1, e2
    r = np.asarray(rest, np.float64)
    r = r - r.mean(0)
    cross = float((r[:, 0] * q[:, 1] - r[:, 1] * q[:, 0]).sum())
    dot = float((r[:, 0] * q[:, 0] + r[:, 1] * q[:, 1]).sum())
    return math.atan2(cross, dot)


def expected_headings(frames: Sequence[int], subjects: Sequence[int],
                      headings: Sequence[float], max_gap: float = math.inf
                      ) -> list[float | None]:
    """Per fit, the heading its track's neighbours expect (module docstring), None where
    the subject has no other fit within ``max_gap`` frames or its two neighbours face nearly
    opposite ways."""
    tracks: dict[int, list[int]] = defaultdict(list)
    for i in sorted(range(len(frames)), key=lambda i: frames[i]):
        tracks[int(subjects[i])].append(i)
    out: list[float | None] = [None] * len(frames)
    for rows in tracks.values():
        for j, i in enumerate(rows):
            near = [headings[rows[n]] for n in (j - 1, j + 1) if 0 <= n < len(rows)
                    and abs(frames[rows[n]] - frames[i]) <= max_gap]
            if len(near) == 1:
                out[i] = near[0]
            elif len(near) == 2 and abs(wrap_angle(near[1] - near[0])) <= AMBIGUOUS:
                out[i] = wrap_angle(near[0] + wrap_angle(near[1] - near[0]) / 2)
    return out


def turns(frames: Sequence[int], subjects: Sequence[int], headings: Sequence[float],
          max_gap: float = math.inf, max_turn: float = MAX_TURN) -> dict[int, float]:
    """Fit index -> the turn (radians about up) that takes it to the heading its neighbours
    (within ``max_gap`` frames) expect, for the fits more than ``max_turn`` from it."""
    out = {}
    for i, want in enumerate(expected_headings(frames, subjects, headings, max_gap)):
        if want is not None and abs(wrap_angle(want - headings[i])) > max_turn:
            out[i] = wrap_angle(want - headings[i])
    return out


def turned_pose(keypoints: np.ndarray, angle: float, up: Sequence[float]) -> np.ndarray:
    """The pose (K, 3) turned by ``angle`` radians about the up axis through its centroid."""
    p = torch.as_tensor(np.asarray(keypoints, np.float64))
    centre = p.mean(0)
    axis = torch.tensor(up, dtype=torch.float64)
    return (rotate_about_up(p - centre, angle, axis) + centre).numpy()
