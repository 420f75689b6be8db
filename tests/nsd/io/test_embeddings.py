"""Embedding tables: streamed Parquet and npz read back equal; columns are appended in order."""

from __future__ import annotations

import numpy as np
import pytest

from nsd.io.embeddings import EmbeddingWriter, add_columns, read_embeddings


def _rows(n, start, rng):
    return {
        "id": np.arange(start, start + n, dtype=np.int64),
        "camera": np.array(["cam0", "cam10"] * n)[:n],
        "score": rng.random(n).astype(np.float32),
        "app": rng.standard_normal((n, 6)).astype(np.float32),
    }


@pytest.mark.parametrize("fmt", ["parquet", "npz"])
def test_streamed_table_reads_back_equal(tmp_path, fmt):
    rng = np.random.default_rng(0)
    batches = [_rows(n, s, rng) for n, s in ((3, 0), (4, 3), (0, 7), (5, 7))]
    w = EmbeddingWriter(tmp_path / "embeddings", fmt, row_group_size=4)
    for b in batches:
        w.write(b)
    path = w.close()
    assert path.name == f"embeddings.{fmt}" and w.rows == 12
    got = read_embeddings(tmp_path)  # the folder is enough
    for k in batches[0]:
        np.testing.assert_array_equal(got[k], np.concatenate([b[k] for b in batches]))
    assert got["app"].shape == (12, 6) and got["app"].dtype == np.float32
    if fmt == "parquet":
        import pyarrow.parquet as pq

        meta = pq.ParquetFile(path).metadata  # whole row groups, written while streaming
        assert [meta.row_group(g).num_rows for g in range(meta.num_row_groups)] == [4, 4, 4]


@pytest.mark.parametrize("fmt", ["parquet", "npz"])
def test_add_columns_appends_in_row_order(tmp_path, fmt):
    rng = np.random.default_rng(1)
    w = EmbeddingWriter(tmp_path / "embeddings", fmt, row_group_size=2)
    w.write(_rows(5, 0, rng))
    path = w.close()
    before = read_embeddings(path)
    codes = rng.standard_normal((5, 3)).astype(np.float32)
    add_columns(path, {"texture": codes, "flag": np.arange(5) % 2 == 0})
    after = read_embeddings(path)
    np.testing.assert_array_equal(after["texture"], codes)
    np.testing.assert_array_equal(after["flag"], np.arange(5) % 2 == 0)
    for k, v in before.items():
        np.testing.assert_array_equal(after[k], v)
    with pytest.raises(ValueError, match="has 4 rows, the table has 5"):
        add_columns(path, {"bad": np.zeros(4)})
    with pytest.raises(ValueError, match="exists already"):
        add_columns(path, {"texture": codes})
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left


def test_empty_table_keeps_its_columns(tmp_path):
    w = EmbeddingWriter(tmp_path / "e", "parquet")
    empty = {"id": np.zeros(0, np.int64), "app": np.zeros((0, 4), np.float32)}
    w.close(empty_columns=empty)
    got = read_embeddings(tmp_path / "e.parquet")
    assert got["id"].shape == (0,) and got["app"].shape == (0, 4)


def test_missing_table_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="neither embeddings"):
        read_embeddings(tmp_path)
