"""Atomic writes: nothing half-written under the final name, stale partials cleaned up."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from nsd.core.atomic import atomic_directory, atomic_save_npz, atomic_write_text


def test_directory_appears_only_on_success(tmp_path):
    final = tmp_path / "out"
    with pytest.raises(RuntimeError), atomic_directory(final) as tmp:
        (tmp / "a.txt").write_text("x")
        raise RuntimeError("boom")
    assert not final.exists()
    assert not list(tmp_path.glob(".out.partial-*"))
    with atomic_directory(final) as tmp:
        (tmp / "a.txt").write_text("y")
    assert (final / "a.txt").read_text() == "y"
    with atomic_directory(final) as tmp:  # overwrite replaces the whole folder
        (tmp / "b.txt").write_text("z")
    assert sorted(p.name for p in final.iterdir()) == ["b.txt"]
    with pytest.raises(FileExistsError), atomic_directory(final, overwrite=False):
        pass


def test_killed_writer_leaves_only_a_partial_that_is_cleaned(tmp_path):
    code = (
        "import os, sys, time\n"
        "from nsd.core.atomic import atomic_directory\n"
        f"with atomic_directory({str(tmp_path / 'out')!r}) as t:\n"
        "    (t / 'a').write_text('x'); print('ready', flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    partials = list(tmp_path.glob(".out.partial-*"))
    assert len(partials) == 1
    # a live writer's partial is not touched by another writer of the same name
    with atomic_directory(tmp_path / "out") as t:
        (t / "b").write_text("y")
    assert partials[0].exists()
    proc.kill()
    proc.wait()
    assert not (tmp_path / "out" / "a").exists()
    with atomic_directory(tmp_path / "out") as t:  # the dead writer's partial is removed
        (t / "c").write_text("z")
    assert not partials[0].exists()


def test_atomic_write_text(tmp_path):
    atomic_write_text(tmp_path / "f.txt", "hello")
    assert (tmp_path / "f.txt").read_text() == "hello"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]
    assert os.stat(tmp_path / "f.txt").st_size == 5


@pytest.mark.parametrize("level", [1, 6, 9])
def test_npz_at_any_compression_level_loads_as_numpy_writes_it(tmp_path, level):
    """atomic_save_npz writes what np.load reads, equal to np.savez_compressed's content; a
    faster level makes a file no smaller than the default's on the same data."""
    rng = np.random.default_rng(level)
    arrays = {"images": rng.integers(0, 8, (20, 16, 16, 3), dtype=np.uint8),
              "ids": np.arange(20, dtype=np.int64), "x": rng.random((3, 5))}
    atomic_save_npz(tmp_path / "a.npz", compresslevel=level, **arrays)
    np.savez_compressed(tmp_path / "b.npz", **arrays)
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert sorted(a.files) == sorted(b.files) == sorted(arrays)
    for k, v in arrays.items():
        assert a[k].dtype == v.dtype
        np.testing.assert_array_equal(a[k], v)
    size, default = (tmp_path / "a.npz").stat().st_size, (tmp_path / "b.npz").stat().st_size
    assert size >= default if level == 1 else size <= default + 64
