r"""Front and back from the direction of travel.

Silhouettes hardly tell a body from the same body turned front to back: in about a tenth of
the subject-frames of the synthetic bipeds the inversion finds the pose with its left
keypoints where the right ones are (``mirrored_share`` in ``tools/bench_keypoints.py``;
docs/netepu.md). People and animals that travel mostly travel forwards, so a subject that
moves at ``min_speed`` body radii per second or faster and whose fit faces against its
travel is relabelled: each keypoint takes the position of its counterpart on the other
side (:meth:`nsd.synth.skeleton.Species.mirror_index`). Positions do not change; only which
side is which.

With :math:`L` the keypoints on the left and :math:`m` the mirror index, a pose faces

.. math::
    f = P_u \Big(\tfrac{1}{|L|} \sum_{k \in L} x_k - x_{m(k)}\Big) \times u,

the body's left-right axis on the ground plane (:math:`P_u` removes the component along the
up axis :math:`u`) turned a quarter turn about :math:`u`. Its travel is the ground-plane
velocity of the triangulated silhouette centroids :math:`p` of the subject
(:func:`nsd.export.positions.triangulate_positions`) :math:`d` frames before and after,

.. math::
    v = P_u \frac{p(t + d) - p(t - d)}{2 d / \text{fps}},

and the fit is relabelled when :math:`|v| \ge` ``min_speed`` :math:`\cdot r` and
:math:`f \cdot v < 0`. On the synthetic scenes' ground truth the bipeds face their travel
in 93-100 % of the frames where they move at 0.6 radii per second or faster, in 70-100 %
below (docs/netepu.md "Front and back").

Where it pays is measured per species (``netepu.keypoints.travel_speed: auto``,
:data:`netepu.pipeline.subject_keypoints.AUTO`): on bipeds, whose front and back cast nearly
the same silhouettes. A quadruped's left-right axis faced its travel in only 75-91 % of its
fast frames, and the rule made its keypoints worse (206 -> 214 mm), so it is off there.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["TRAVEL_SECONDS", "face_travel", "facing", "travel_velocity"]

TRAVEL_SECONDS = 0.2  # d: the travel is measured over this long before and after a frame


def _ground(x: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``x`` (3,) without its component along the unit ``up``."""
    return x - (x @ up) * up


def facing(keypoints: np.ndarray, left: Sequence[int], mirror: Sequence[int],
           up: np.ndarray) -> np.ndarray:
    """The module docstring's :math:`f` of one pose (K, 3), unnormalised (3,).

    Example:
        >>> kp = np.array([[0.0, 0.2, 1.0], [0.0, -0.2, 1.0]])  # a left and a right keypoint
        >>> facing(kp, [0], [1, 0], np.array([0.0, 0.0, 1.0]))  # left along +y: faces +x
        array([0.4, 0. , 0. ])
    """
    kp = np.asarray(keypoints, np.float64)
    lateral = (kp[list(left)] - kp[[mirror[k] for k in left]]).mean(0)
    return np.cross(_ground(lateral, up), up)


def travel_velocity(positions: dict[tuple[int, int], tuple[np.ndarray, int]], frame: int,
                    subject: int, d: int, fps: float, up: np.ndarray) -> np.ndarray | None:
    """The module docstring's :math:`v` of ``subject`` at ``frame`` from ``positions``
    (``(frame, subject) -> (position (3,), views)``); None where either end is missing."""
    before, after = positions.get((frame - d, subject)), positions.get((frame + d, subject))
    if before is None or after is None:
        return None
    return _ground((after[0] - before[0]) * fps / (2 * d), up)


def face_travel(keypoints: np.ndarray, velocity: np.ndarray | None, left: Sequence[int],
                mirror: Sequence[int], up: np.ndarray, min_speed: float
                ) -> tuple[np.ndarray, bool]:
    """``(keypoints, relabelled)``: the pose (K, 3) relabelled left for right when it moves
    at ``min_speed`` (scene units per second) or faster and faces against ``velocity``
    (module docstring), else unchanged."""
    if velocity is None or min_speed <= 0 or np.linalg.norm(velocity) < min_speed:
        return keypoints, False
    if facing(keypoints, left, mirror, up) @ velocity >= 0:
        return keypoints, False
    return np.asarray(keypoints)[list(mirror)], True
