"""The per-subject embedding table: Parquet (pyarrow), with an ``.npz`` fallback.

One row per subject per camera-frame. Scalar columns are stored as Parquet
scalars; vector columns (shape (rows, D), e.g. ``app``, the appearance vector)
as fixed-size lists of float32, which pandas reads as arrays and
:func:`read_embeddings` returns as (rows, D) arrays.

:class:`EmbeddingWriter` streams: rows are buffered and written as Parquet row
groups of ``row_group_size`` rows, so a table of any length is written with
bounded memory. The ``.npz`` fallback (``format="npz"``, or when pyarrow cannot
be imported) keeps the table in memory until :meth:`EmbeddingWriter.close`
(about 0.6 KB per row with 128-d vectors; 80,000 rows are 50 MB) because an
``.npz`` member cannot be appended to.

:func:`add_columns` appends columns to an existing table (e.g. NeTePu texture
codes computed later for the same rows), atomically.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nsd.core.atomic import atomic_save_npz

try:  # optional at run time: without pyarrow the table falls back to .npz (module docstring)
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError:  # pragma: no cover - pyarrow is a core dependency
    pa = pq = None

__all__ = [
    "EmbeddingWriter", "add_columns", "embeddings_path", "read_embeddings", "read_tracklets",
]


def _have_pyarrow() -> bool:
    return pq is not None


def _arrow_column(values: np.ndarray):
    """numpy (rows,) or (rows, D) -> pyarrow array (fixed-size list for 2-D)."""
    values = np.asarray(values)
    if values.ndim == 1:
        if values.dtype.kind in "US":
            return pa.array(values.astype(str).tolist(), pa.string())
        return pa.array(values)
    if values.ndim == 2:
        flat = pa.array(np.ascontiguousarray(values, np.float32).reshape(-1))
        return pa.FixedSizeListArray.from_arrays(flat, values.shape[1])
    raise ValueError(f"columns must be (rows,) or (rows, D), got shape {values.shape}")


def _numpy_column(col) -> np.ndarray:
    """pyarrow (chunked) array -> numpy, fixed-size lists as (rows, D)."""
    if hasattr(col, "combine_chunks"):
        col = col.combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        d = col.type.list_size
        return np.asarray(col.flatten().to_numpy(zero_copy_only=False)).reshape(-1, d)
    if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
        return np.asarray(col.to_pylist(), dtype=str)
    return col.to_numpy(zero_copy_only=False)


class EmbeddingWriter:
    """Stream rows into ``<stem>.parquet`` (or ``<stem>.npz``).

    Args:
        stem: path without extension (e.g. ``out/embeddings``).
        format: ``"parquet"`` (falls back to ``"npz"`` without pyarrow) or ``"npz"``.
        row_group_size: rows per Parquet row group.

    Every call to :meth:`write` must give the same columns with the same dtypes
    and vector sizes.
    """

    def __init__(
        self, stem: str | os.PathLike, format: str = "parquet", row_group_size: int = 4096
    ) -> None:
        if format not in ("parquet", "npz"):
            raise ValueError(f"embeddings format must be 'parquet' or 'npz', got {format!r}")
        if format == "parquet" and not _have_pyarrow():
            format = "npz"
        self.format = format
        self.path = Path(f"{stem}.{format}")
        self.row_group_size = row_group_size
        self.rows = 0
        self._buffer: list[dict[str, np.ndarray]] = []
        self._buffered = 0
        self._writer = None
        self._schema = None

    def write(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append rows given as equally long columns (rows,) or (rows, D)."""
        lengths = {len(v) for v in columns.values()}
        if len(lengths) != 1:
            sizes = {k: len(v) for k, v in columns.items()}
            raise ValueError(f"columns differ in length: {sizes}")
        n = lengths.pop()
        if n == 0:
            return
        self._buffer.append({k: np.asarray(v) for k, v in columns.items()})
        self._buffered += n
        self.rows += n
        if self.format == "parquet" and self._buffered >= self.row_group_size:
            self._flush()

    def _concat(self) -> dict[str, np.ndarray]:
        keys = list(self._buffer[0])
        return {k: np.concatenate([b[k] for b in self._buffer]) for k in keys}

    def _flush(self, final: bool = False) -> None:
        """Write whole row groups (and, if ``final``, the remainder) of the buffer."""

        if not self._buffer:
            return
        cols = self._concat()
        n = self._buffered if final else self._buffered // self.row_group_size * self.row_group_size
        if n == 0:
            return
        table = pa.table({k: _arrow_column(v[:n]) for k, v in cols.items()})
        if self._writer is None:
            self._schema = table.schema
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(self.path, self._schema)
        self._writer.write_table(table.cast(self._schema), row_group_size=self.row_group_size)
        rest = {k: v[n:] for k, v in cols.items()}
        self._buffered -= n
        self._buffer = [rest] if self._buffered else []

    def close(self, empty_columns: Mapping[str, np.ndarray] | None = None) -> Path:
        """Finish the file; without rows, write ``empty_columns`` (zero-row arrays) instead."""
        if self.rows == 0 and empty_columns is not None:
            self._buffer = [{k: np.asarray(v) for k, v in empty_columns.items()}]
            if self.format == "parquet":

                table = pa.table({k: _arrow_column(v) for k, v in self._buffer[0].items()})
                pq.write_table(table, self.path)
                return self.path
        if self.format == "npz":
            atomic_save_npz(self.path, **(self._concat() if self._buffer else {}))
        else:
            self._flush(final=True)
            if self._writer is not None:
                self._writer.close()
        return self.path


def embeddings_path(path: str | os.PathLike) -> Path:
    """The table file: ``path`` itself, or ``embeddings.parquet``/``.npz`` in an export folder."""
    path = Path(path)
    if path.is_dir():
        for name in ("embeddings.parquet", "embeddings.npz"):
            if (path / name).is_file():
                return path / name
        raise FileNotFoundError(f"{path} holds neither embeddings.parquet nor embeddings.npz")
    if not path.is_file():
        raise FileNotFoundError(f"embedding table {path} does not exist")
    return path


def read_embeddings(
    path: str | os.PathLike, columns: list[str] | None = None,
    optional: Sequence[str] = (),
) -> dict[str, np.ndarray]:
    """All (or the named) columns of a table as numpy arrays; vectors as (rows, D); the
    ``optional`` columns too where the table has them (an older export's may not)."""
    path = embeddings_path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            names = [*(columns or z.files), *(c for c in optional if c in z.files)]
            return {k: z[k] for k in names}
    if columns is not None and optional:
        have = set(pq.ParquetFile(path).schema_arrow.names)
        columns = [*columns, *(c for c in optional if c in have)]
    table = pq.read_table(path, columns=columns)
    return {name: _numpy_column(table.column(name)) for name in table.column_names}


def read_tracklets(path: str | os.PathLike) -> dict[tuple[int, int], int] | None:
    """``(frame, subject_id) -> tracklet_id`` of an export's table (the tracker's pieces of
    each track, :mod:`nsd.inference.tracking`); None where there are none: an export made
    before tracklets, or a folder without the table."""
    try:
        t = read_embeddings(path, ["frame", "subject_id"], optional=("tracklet_id",))
    except FileNotFoundError:
        return None
    if "tracklet_id" not in t:
        return None
    keys = zip(t["frame"].tolist(), t["subject_id"].tolist(), strict=True)
    return dict(zip(keys, t["tracklet_id"].tolist(), strict=True))


def add_columns(path: str | os.PathLike, columns: Mapping[str, np.ndarray]) -> Path:
    """Append columns (rows,) or (rows, D) to a table, in row order, atomically.

    Parquet tables are rewritten one row group at a time, so only the new
    columns and one row group are in memory.

    Raises:
        ValueError: a column's length differs from the table's, or it exists already.
    """
    path = embeddings_path(path)
    new = {k: np.asarray(v) for k, v in columns.items()}
    if path.suffix == ".npz":
        table = read_embeddings(path)
        _check_new(path, table, len(next(iter(table.values()))) if table else 0, new)
        atomic_save_npz(path, **table, **new)
        return path
    src = pq.ParquetFile(path)
    _check_new(path, dict.fromkeys(src.schema_arrow.names), src.metadata.num_rows, new)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    writer = None
    try:
        start = 0
        for g in range(src.num_row_groups):
            group = src.read_row_group(g)
            n = group.num_rows
            for k, v in new.items():
                group = group.append_column(k, _arrow_column(v[start : start + n]))
            start += n
            if writer is None:
                writer = pq.ParquetWriter(tmp, group.schema)
            writer.write_table(group)
        if writer is None:  # a table without row groups
            empty = src.read()
            for k, v in new.items():
                empty = empty.append_column(k, _arrow_column(v))
            pq.write_table(empty, tmp)
        else:
            writer.close()
            writer = None
        os.replace(tmp, path)
    finally:
        if writer is not None:
            writer.close()
        if tmp.exists():
            tmp.unlink()
    return path


def _check_new(path: Path, table: Mapping[str, Any], rows: int, new: Mapping[str, np.ndarray]):
    for k, v in new.items():
        if k in table:
            raise ValueError(f"{path}: column {k!r} exists already")
        if len(v) != rows:
            raise ValueError(f"{path}: column {k!r} has {len(v)} rows, the table has {rows}")
