r"""Which species each subject is, where a run holds several: the body that fits its masks.

In a run of several species (``netepu.species=mixed``, or ``auto`` on a scene that declares
more than one; :func:`netepu.pipeline.species_models.resolve_scene_models`) the keypoints
stage inverts every subject-frame once with each species' geometry model, on the same masks,
occluders and loss points (the points are drawn from the frame's seed). Each fit ends with
its silhouette loss, the occlusion-aware BCE of the rendered silhouettes against the observed
ones (:mod:`netepu.geometry.inverse`): a measure of the masks, not of the model, so the losses
of two bodies on one subject-frame compare. A cow's silhouette cannot be drawn by a standing
biped, nor a biped's by a cow.

* A fitted subject-frame takes the species of the lowest loss, then the most frequent species
  of it and its tracklet's fitted frames within ``window`` fitted frames on either side (its
  own on a tie): one frame whose masks were poor (a huddle) does not flip the body, a track that
  swapped individuals of two species follows the swap.
* Every row of the export then takes a species (:func:`species_of_rows`): its subject-frame's
  where it was fitted, otherwise its tracklet's at the nearest fitted frame in time (the
  earlier on a tie; the export's ``tracklet_id``, the track cut where the tracker forced a
  link, which may join a biped to a cow), its track's where the tracklet has no fitted
  frame; "" for tracks never fitted.

Each species' keypoints file then holds the subject-frames that took it (:func:`split_fits`),
which that species' texture model codes; identities are assigned within each species.
"""

from __future__ import annotations

import csv
import io
import os
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from netepu.reid.identities import majority_in_window, nearest_in_time, row_groups
from nsd.core.atomic import atomic_save_npz, atomic_write_text

__all__ = ["SpeciesChoice", "choose_species", "read_species_csv", "species_of_rows",
           "split_fits", "write_species_csv"]

WINDOW = 2  # fitted frames on either side whose vote a subject-frame's species takes


@dataclass(frozen=True)
class SpeciesChoice:
    """The species of one fitted subject-frame and the final loss of every species' fit."""

    frame: int
    subject_id: int
    species: str
    losses: dict[str, float]


def _fits(path: str | os.PathLike) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def choose_species(fits: Mapping[str, str | os.PathLike], window: int = WINDOW,
                   tracklets: Mapping[tuple[int, int], int] | None = None
                   ) -> list[SpeciesChoice]:
    """The species of every subject-frame fitted with each species' model.

    Args:
        fits: species -> ``keypoints3d.npz`` of the same subject-frames fitted with that
            species' geometry model (:mod:`nsd.io.keypoints`).
        window: fitted frames of the track on either side that vote (0: each frame alone).
        tracklets: (frame, subject) -> the export's ``tracklet_id``: the votes are the
            tracklet's, not the whole track's (a forced link may join a biped to a cow);
            None: the track's.

    Returns:
        one :class:`SpeciesChoice` per subject-frame fitted by every species, in
        (frame, subject) order.
    """
    names = sorted(fits)
    loss: dict[tuple[int, int], dict[str, float]] = defaultdict(dict)
    for s in names:
        z = _fits(fits[s])
        for t, sid, x in zip(z["subject_frame"].tolist(), z["subject_id"].tolist(),
                             z["subject_loss"].tolist(), strict=True):
            loss[(t, sid)][s] = float(x)
    keys = sorted(k for k, v in loss.items() if len(v) == len(names))
    by_track: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for k in keys:
        by_track[k[1] if tracklets is None else tracklets.get(k, -1 - k[1])].append(k)
    chosen = {}
    for frames in by_track.values():  # each frame's body of lowest loss, voted along the track
        own = [min(names, key=lambda s, k=k: loss[k][s]) for k in frames]
        chosen |= dict(zip(frames, majority_in_window(own, window), strict=True))
    return [SpeciesChoice(t, sid, chosen[(t, sid)], loss[(t, sid)]) for t, sid in keys]


def split_fits(fits: Mapping[str, str | os.PathLike], choices: list[SpeciesChoice],
               out: Mapping[str, str | os.PathLike]) -> dict[str, int]:
    """Write, per species, its ``keypoints3d.npz`` with only the subject-frames that took it
    (their rows and keypoints as that species' model fitted them).

    Returns:
        species -> subject-frames kept.
    """
    species_of = {(c.frame, c.subject_id): c.species for c in choices}
    kept = {}
    for s, path in fits.items():
        z = _fits(path)
        ends = np.cumsum(z["subject_views"])
        starts = ends - z["subject_views"]
        keep = np.array([species_of.get((t, sid)) == s for t, sid in
                         zip(z["subject_frame"].tolist(), z["subject_id"].tolist(), strict=True)],
                        bool)
        rows = np.concatenate([np.arange(a, b) for a, b, k in zip(starts, ends, keep, strict=True)
                               if k] or [np.zeros(0, np.int64)]).astype(np.int64)
        arrays = {k: v[keep] for k, v in z.items() if k.startswith("subject_")}
        arrays |= {"id": z["id"][rows], "keypoints": z["keypoints"][rows]}
        atomic_save_npz(Path(out[s]), **arrays)
        kept[s] = int(keep.sum())
    return kept


def species_of_rows(subject_id: np.ndarray, frame: np.ndarray, choices: list[SpeciesChoice],
                    tracklet: np.ndarray | None = None) -> np.ndarray:
    """The species of every row (module docstring): (rows,) object array of str ("" for
    tracks never fitted); ``tracklet`` (rows,): the rows' ``tracklet_id`` (None: an export
    without them, tracks only)."""
    sid = np.asarray(subject_id, np.int64)
    frame = np.asarray(frame, np.int64)
    out = np.full(len(sid), "", object)
    _nearest_choice(out, sid, frame, [(c, c.subject_id) for c in choices])
    if tracklet is not None:
        piece = np.asarray(tracklet, np.int64)
        of = dict(zip(zip(frame.tolist(), sid.tolist(), strict=True), piece.tolist(),
                      strict=True))
        _nearest_choice(out, piece, frame, [(c, of.get((c.frame, c.subject_id), -1))
                                            for c in choices])
    return out


def _nearest_choice(out: np.ndarray, owner: np.ndarray, frame: np.ndarray,
                    owned: list[tuple[SpeciesChoice, int]]) -> None:
    """Into ``out``: each row the species of its owner's (track or tracklet, ``owner``
    (rows,); ``owned``: each choice with its owner) fitted frame nearest in time; owners
    without one are left as they are."""
    by_owner: dict[int, list[SpeciesChoice]] = defaultdict(list)
    for c, o in owned:
        by_owner[o].append(c)
    rows_of = dict(row_groups(owner))
    for o, fitted in by_owner.items():
        rows = rows_of.get(o)
        if rows is None:
            continue
        fitted.sort(key=lambda c: c.frame)
        pick = nearest_in_time(np.array([c.frame for c in fitted]), frame[rows])
        out[rows] = [fitted[i].species for i in pick]


def write_species_csv(path: str | os.PathLike, choices: list[SpeciesChoice]) -> None:
    """``species.csv``: frame, subject_id, species, and every species' final loss."""
    names = sorted({s for c in choices for s in c.losses})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "subject_id", "species", *(f"loss_{s}" for s in names)])
    for c in choices:
        w.writerow([c.frame, c.subject_id, c.species, *(f"{c.losses[s]:.5f}" for s in names)])
    atomic_write_text(Path(path), buf.getvalue())


def read_species_csv(path: str | os.PathLike) -> list[SpeciesChoice]:
    """The choices of a ``species.csv`` (:func:`write_species_csv`)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    return [SpeciesChoice(int(r["frame"]), int(r["subject_id"]), r["species"],
                          {k.removeprefix("loss_"): float(v) for k, v in r.items()
                           if k.startswith("loss_")})
            for r in rows]
