"""``identities.csv``: one identity per exported row (the identities stage of ``nsd-run``).

Columns ``id`` (the export's annotation id), ``camera``, ``frame``, ``subject_id`` and
``identity`` (-1: none), one row per exported subject, comma-separated with a header
(datasets/export.md).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nsd.core.atomic import atomic_write_text

__all__ = ["COLUMNS", "identity_by_row", "read_identities", "write_identities"]

COLUMNS = ("id", "camera", "frame", "subject_id", "identity")
_INT = {"id", "frame", "subject_id", "identity"}


def write_identities(path: Path, columns: dict[str, Sequence]) -> None:
    """Write the :data:`COLUMNS` of ``columns`` (equal lengths) atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    w.writerows(zip(*(list(columns[c]) for c in COLUMNS), strict=True))
    atomic_write_text(path, buf.getvalue())


def read_identities(path: Path) -> dict[str, np.ndarray]:
    """The columns of an ``identities.csv`` (integers as int64, ``camera`` as str)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {c: np.array([r[c] for r in rows], dtype=np.int64 if c in _INT else object)
            for c in COLUMNS}


def identity_by_row(path: Path) -> dict[int, int]:
    """Export annotation id -> identity (-1: none) of an ``identities.csv``."""
    ids = read_identities(path)
    return dict(zip(ids["id"].tolist(), ids["identity"].tolist(), strict=True))
