"""tools/benchlib.py: the commit a report or a shipped file records, a run's evaluations."""

from __future__ import annotations

import shutil
import subprocess

import pytest

import tools.benchlib as benchlib

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(repo, *args):
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=repo,
                   check=True, capture_output=True)


@needs_git
def test_git_commit_is_dirty_unless_only_the_ignored_files_changed(tmp_path, monkeypatch):
    """A changed tracked file makes the commit ``+dirty``; the files a tool writes itself
    (``ignore``) do not, another changed file still does, and an untracked one never."""
    for name in ("model.pt", "models.json", "code.py"):
        (tmp_path / name).write_text("0")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "first")
    monkeypatch.setattr(benchlib, "ROOT", tmp_path)
    head = benchlib.git_commit()
    assert head and "+" not in head and head != "unknown"
    (tmp_path / "new.txt").write_text("untracked")
    assert benchlib.git_commit() == head
    (tmp_path / "model.pt").write_text("1")
    (tmp_path / "models.json").write_text("1")
    assert benchlib.git_commit() == head + "+dirty"
    assert benchlib.git_commit(ignore=(tmp_path / "model.pt", tmp_path / "models.json")) == head
    assert benchlib.git_commit(ignore=(tmp_path / "model.pt",)) == head + "+dirty"
    (tmp_path / "code.py").write_text("1")
    assert benchlib.git_commit(ignore=(tmp_path / "model.pt", tmp_path / "models.json")) == (
        head + "+dirty")


def test_evaluations_one_row_per_step_in_order(tmp_path):
    """The rows where the key is logged, one per step: the final evaluation, logged again at
    the last step, is kept once; training rows and rows of other evaluations are left out."""
    (tmp_path / "metrics.csv").write_text(
        "step,minutes,loss,eval/heldout_poses/iou,eval/other\n"
        "10,0.1,0.5,,\n"
        "20,0.2,0.4,0.80,1\n"
        "30,0.3,0.3,,2\n"
        "40,0.4,0.2,0.90,\n"
        "40,0.4,,0.90,3\n")
    rows = benchlib.evaluations(tmp_path)
    assert [r["step"] for r in rows] == ["20", "40"]
    assert rows[-1]["eval/other"] == "3"  # the last logged row of a step
    assert [r["step"] for r in benchlib.evaluations(tmp_path, "eval/other")] == ["20", "30", "40"]
