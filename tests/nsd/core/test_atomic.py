"""Atomic writes: nothing half-written under the final name, stale partials cleaned up."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from nsd.core.atomic import atomic_directory, atomic_write_text


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
