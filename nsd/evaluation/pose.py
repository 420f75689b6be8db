"""Keypoint accuracy: MPJPE of 3D keypoints, and of an export's recovered keypoints against a
synthetic scene (subjects matched to ground-truth individuals by mask IoU,
:func:`nsd.evaluation.identity.ground_truth_identities`).
"""

from __future__ import annotations

import os
from collections import Counter, defaultdict
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np
from torch import Tensor

from nsd.core.errors import ConfigError
from nsd.evaluation.identity import ground_truth_identities
from nsd.io.ground_truth import GroundTruth

__all__ = ["keypoint_error", "mirror_errors", "mpjpe", "species_accuracy",
           "subject_frame_errors", "subject_truth"]


def mpjpe(pred: Tensor, target: Tensor) -> Tensor:
    """Mean per-joint position error of keypoints (..., K, 3) -> scalar (input units)."""
    return (pred - target).double().norm(dim=-1).mean()


def subject_truth(export: str | os.PathLike, scene: str | os.PathLike,
                  frames: Collection[int] | None = None) -> dict[tuple[int, int], int]:
    """(frame, subject_id) -> the ground-truth individual most of the subject-frame's rows
    match (:func:`nsd.evaluation.identity.ground_truth_identities`: every row's mask decoded
    and matched, so a caller scoring several files of one export computes it once);
    ``frames``: only these frames (None: all)."""
    votes: dict[tuple[int, int], Counter] = defaultdict(Counter)
    for _cam, t, sid, ident in ground_truth_identities(export, scene, frames=frames).values():
        votes[(t, sid)][ident] += 1
    return {k: v.most_common(1)[0][0] for k, v in votes.items()}


def _matched(export: str | os.PathLike, scene: str | os.PathLike,
             keypoints: str | os.PathLike, other_bodies: bool = False,
             matched: dict[tuple[int, int], int] | None = None,
             ) -> tuple[int, list[tuple[np.ndarray, np.ndarray]]]:
    """``(subject-frames in the file, (inverted, true) keypoints (K, 3) of each one matched)``:
    each inverted subject-frame is matched to the ground-truth individual most of its rows
    match (:func:`subject_truth`); unmatched ones are left out, and with ``other_bodies``
    those matched to an individual of another number of keypoints (another species);
    ``matched``: :func:`subject_truth`, if computed already."""
    truth = GroundTruth.load(scene).scene.keypoints3d
    with np.load(keypoints) as z:
        frames, sids, kps = z["subject_frame"], z["subject_id"], z["subject_keypoints"]
    if matched is None:  # the ground truth of the fitted frames alone
        matched = subject_truth(export, scene, set(frames.tolist()))
    pairs = []
    for t, sid, kp in zip(frames.tolist(), sids.tolist(), kps, strict=True):
        if (t, sid) not in matched:
            continue
        gt = truth[matched[(t, sid)]][t]
        if gt.shape != kp.shape:
            if other_bodies:
                continue
            raise ConfigError(f"keypoints: {kp.shape[0]} keypoints, the scene has {gt.shape[0]}")
        pairs.append((kp, gt))
    return len(frames), pairs


def species_accuracy(export: str | os.PathLike, scene: str | os.PathLike,
                     choices: Sequence[Any], matched: dict[tuple[int, int], int] | None = None
                     ) -> dict[str, float]:
    """Share of the subject-frames whose chosen species (``choices``: items with ``frame``,
    ``subject_id``, ``species``, :class:`netepu.pipeline.species_choice.SpeciesChoice`) is the
    species of the ground-truth individual they match, over those matched (``scored``;
    ``matched``: :func:`subject_truth`, if computed already)."""
    individuals = GroundTruth.load(scene).scene.individuals
    body = {int(i["identity_id"]): str(i["species"]) for i in individuals}
    matched = subject_truth(export, scene) if matched is None else matched
    right = [c.species == body[matched[(c.frame, c.subject_id)]] for c in choices
             if (c.frame, c.subject_id) in matched]
    return {"scored": float(len(right)),
            "accuracy": float(np.mean(right)) if right else float("nan")}


def _mm(kp: np.ndarray, gt: np.ndarray) -> float:
    return 1000 * float(np.linalg.norm(kp - gt, axis=-1).mean())


def subject_frame_errors(
    export: str | os.PathLike, scene: str | os.PathLike, keypoints: str | os.PathLike,
    other_bodies: bool = False, matched: dict[tuple[int, int], int] | None = None,
) -> tuple[int, list[float]]:
    """``(subject-frames in the file, MPJPE in mm of each one matched)`` (matched as in
    :func:`_matched`; unmatched ones are left out)."""
    inverted, pairs = _matched(export, scene, keypoints, other_bodies, matched)
    return inverted, [_mm(kp, gt) for kp, gt in pairs]


def mirror_errors(
    export: str | os.PathLike, scene: str | os.PathLike, keypoints: str | os.PathLike,
    mirror: Sequence[int],
) -> list[tuple[float, float]]:
    """Per matched subject-frame, MPJPE in mm as inverted and with its left and right
    keypoints swapped (``mirror``: :meth:`nsd.synth.skeleton.Species.mirror_index`): a fit
    far off as inverted and close once swapped is the body turned front to back."""
    index = np.asarray(mirror)
    return [(_mm(kp, gt), _mm(kp[index], gt)) for kp, gt in _matched(export, scene, keypoints)[1]]


def keypoint_error(
    export: str | os.PathLike, scene: str | os.PathLike, keypoints: str | os.PathLike,
    other_bodies: bool = False, matched: dict[tuple[int, int], int] | None = None,
) -> dict[str, float]:
    """MPJPE (mm) of the inverted subjects against a synthetic scene's 3D keypoints, mean and
    median over the matched subject-frames (:func:`subject_frame_errors`); unmatched ones
    (and with ``other_bodies``, those matched to an individual of another species) are
    counted but not scored."""

    inverted, errors = subject_frame_errors(export, scene, keypoints, other_bodies, matched)
    return {
        "inverted": float(inverted),
        "scored": float(len(errors)),
        "mpjpe_mm": float(np.mean(errors)) if errors else float("nan"),
        "mpjpe_mm_median": float(np.median(errors)) if errors else float("nan"),
    }
