"""Tracks in the MOTChallenge text format: one file per camera (sequence).

Each line is one box of one track in one frame, 10 comma-separated values::

    <frame>,<id>,<bb_left>,<bb_top>,<bb_width>,<bb_height>,<conf>,<x>,<y>,<z>

as in MOTChallenge result files (MOT16/17/20, read by TrackEval and
py-motmetrics): ``frame`` is 1-based (footage frame index + 1), ``id`` a
positive track id, the box in pixels with the image's top-left pixel at (1, 1)
(so ``bb_left`` = COCO ``x`` + 1), ``conf`` the detection score, and
``x, y, z`` the individual's world position in metres where it is known (the tracks under
the final identities: :mod:`nsd.export.positions`), else -1. Lines are sorted by frame.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

__all__ = ["MOT_COLUMNS", "MotWriter", "format_mot_line", "read_mot", "write_identity_tracks"]

MOT_COLUMNS = ("frame", "id", "bb_left", "bb_top", "bb_width", "bb_height", "conf", "x", "y", "z")


def format_mot_line(frame: int, track: int, box: Sequence[float], conf: float,
                    world: Sequence[float] | None = None) -> str:
    """One MOTChallenge line for footage frame ``frame`` (0-based) and a COCO box [x, y, w, h];
    ``world``: the position (x, y, z) in metres, or None (-1, -1, -1).

    Example:
        >>> format_mot_line(0, 3, [10.0, 20.0, 5.0, 8.0], 0.91)
        '1,3,11.00,21.00,5.00,8.00,0.9100,-1,-1,-1'
        >>> format_mot_line(0, 3, [10.0, 20.0, 5.0, 8.0], 0.91, (0.5, -1.25, 0.0))
        '1,3,11.00,21.00,5.00,8.00,0.9100,0.500000,-1.250000,0.000000'
    """
    if track < 1:
        raise ValueError(f"MOTChallenge track ids are positive, got {track}")
    x, y, w, h = (float(v) for v in box)
    xyz = "-1,-1,-1" if world is None else ",".join(f"{float(v):.6f}" for v in world)
    return f"{frame + 1},{track},{x + 1:.2f},{y + 1:.2f},{w:.2f},{h:.2f},{conf:.4f},{xyz}"


class MotWriter:
    """Append MOTChallenge lines to ``<folder>/<camera>.txt``, one open file per camera.

    Args:
        folder: where the per-camera files go (created).
        cameras: the camera names (every camera gets a file, even if empty).
    """

    def __init__(self, folder: str | os.PathLike, cameras: Iterable[str]) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.files: dict[str, TextIO] = {
            c: (self.folder / f"{c}.txt").open("w", encoding="ascii") for c in cameras
        }
        self.counts = dict.fromkeys(self.files, 0)

    def write(self, camera: str, frame: int, track: int, box: Sequence[float], conf: float,
              world: Sequence[float] | None = None) -> None:
        """Append one box (frame 0-based, COCO box; world position or None) to the camera's
        file."""
        self.files[camera].write(format_mot_line(frame, track, box, conf, world) + "\n")
        self.counts[camera] += 1

    def close(self) -> None:
        for f in self.files.values():
            f.close()

    def __enter__(self) -> MotWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_mot(path: str | os.PathLike) -> np.ndarray:
    """Parse a MOTChallenge file into a float64 array (L, 10) in :data:`MOT_COLUMNS` order.

    Raises:
        ValueError: a line without 10 numbers, a frame < 1, an id < 1, a negative
            width or height, or two boxes of one track in one frame; the message
            names the file and line.
    """
    path = Path(path)
    rows = []
    seen: set[tuple[int, int]] = set()
    with path.open(encoding="ascii") as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                vals = [float(v) for v in line.split(",")]
            except ValueError as e:
                raise ValueError(f"{path}:{n}: not numbers: {line!r}") from e
            if len(vals) != len(MOT_COLUMNS):
                raise ValueError(f"{path}:{n}: {len(vals)} values, MOTChallenge has 10")
            frame, track, w, h = int(vals[0]), int(vals[1]), vals[4], vals[5]
            if frame < 1 or track < 1 or w < 0 or h < 0:
                raise ValueError(f"{path}:{n}: frame and id must be >= 1, box size >= 0")
            if (frame, track) in seen:
                raise ValueError(f"{path}:{n}: track {track} twice in frame {frame}")
            seen.add((frame, track))
            rows.append(vals)
    return np.asarray(rows, np.float64).reshape(-1, len(MOT_COLUMNS))


def write_identity_tracks(export: str | os.PathLike, row_ids: dict[int, int],
                          folder: str | os.PathLike,
                          positions: dict[tuple[int, int], Any] | None = None) -> dict[str, int]:
    """The export's boxes as MOTChallenge files under other ids: track id = ``row_ids[row] + 1``
    (e.g. the final identities, the same id in every camera). Rows without an id, or with a
    negative one, are left out, and so is a second box of one id in one frame.

    Args:
        export: nsd-export folder (``subjects.coco.json``).
        row_ids: annotation id -> id (>= 0).
        folder: where ``<camera>.txt`` go.
        positions: ``(frame, id)`` -> (world position (3,), views)
            (:func:`nsd.export.positions.triangulate_positions`) for the x, y, z columns.

    Returns:
        Lines written per camera.
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    images = {int(im["id"]): (im["camera"], int(im["frame"])) for im in coco["images"]}
    rows = sorted(
        (images[int(a["image_id"])], row_ids[int(a["id"])], a["bbox"], float(a.get("score", 1)))
        for a in coco["annotations"] if row_ids.get(int(a["id"]), -1) >= 0)
    seen: set[tuple[str, int, int]] = set()
    with MotWriter(folder, sorted({c for c, _ in images.values()})) as w:
        for (camera, frame), ident, box, conf in rows:
            if (camera, frame, ident) not in seen:
                seen.add((camera, frame, ident))
                pos = (positions or {}).get((frame, ident))
                w.write(camera, frame, ident + 1, box, conf, None if pos is None else pos[0])
        return dict(w.counts)
