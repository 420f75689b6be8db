"""One run per folder: the lock, the log, the stale leftovers (nsd/core/run_folder.py)."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap

import pytest

from nsd.core.app import reported
from nsd.core.errors import ConfigError, RunFolderBusyError
from nsd.core.run_folder import LOG_FILE, RunFolder


def test_a_second_run_on_a_held_folder_is_refused_with_the_owner_named(tmp_path):
    """The owner is another process (flock is per open file, so a second process is the
    honest test); it holds the folder until told to stop."""
    code = textwrap.dedent(f"""
        import sys, time
        from nsd.core.run_folder import RunFolder
        with RunFolder({str(tmp_path)!r}, "owner-run", log=False):
            print("held", flush=True)
            sys.stdin.readline()
    """)
    owner = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "held"
        with pytest.raises(RunFolderBusyError, match=rf"pid {owner.pid} .*owner-run"):
            RunFolder(tmp_path, "second").__enter__()
    finally:
        owner.communicate("\n", timeout=30)
    assert owner.returncode == 0  # the first run was unharmed
    with RunFolder(tmp_path, "third", log=False):  # released: the folder is free again
        pass


def test_a_killed_owner_does_not_block_the_next_run(tmp_path):
    code = (f"from nsd.core.run_folder import RunFolder\n"
            f"f = RunFolder({str(tmp_path)!r}, 'doomed', log=False).__enter__()\n"
            "import os; os._exit(9)\n")
    subprocess.run([sys.executable, "-c", code], check=False)
    with RunFolder(tmp_path, "next", log=False):
        pass


def test_stale_partial_folders_are_removed_once_the_lock_is_held(tmp_path):
    (tmp_path / ".train.partial-999999-abc").mkdir()
    (tmp_path / ".scene.json.x1.tmp").write_text("half")
    (tmp_path / "train").mkdir()
    with RunFolder(tmp_path, "run", log=False):
        names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [".lock", "train"]


def test_a_file_given_as_the_folder_is_refused_naming_the_key(tmp_path):
    f = tmp_path / "taken"
    f.write_text("x")
    with pytest.raises(ConfigError, match=r"out: .*taken is a file, not a folder"):
        RunFolder(f, "run").__enter__()


def test_everything_printed_and_logged_goes_to_run_log(tmp_path, capsys):
    logger = logging.getLogger("test_run_folder")
    handler = logging.StreamHandler(sys.stderr)
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        with RunFolder(tmp_path, "run"):
            print("hello stdout")
            print("\rprogress 50%", end="", file=sys.stderr)  # a redraw: not logged
            logger.info("a log line")
    finally:
        logger.removeHandler(handler)
    text = (tmp_path / LOG_FILE).read_text()
    assert "hello stdout" in text and "a log line" in text and "progress" not in text
    assert "hello stdout" in capsys.readouterr().out  # and still on the screen


def test_an_error_is_one_line_on_screen_and_in_run_log(tmp_path, capsys):
    with pytest.raises(SystemExit) as e, reported("nsd-x") as report, \
            RunFolder(tmp_path, "nsd-x") as folder:
        report.attach(folder)
        raise ConfigError("train.batch_size = -1: must be an integer >= 1")
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["nsd-x: error: train.batch_size = -1: must be an integer >= 1"]
    assert "error: train.batch_size = -1" in (tmp_path / LOG_FILE).read_text()


def test_a_bug_is_one_line_on_screen_and_a_traceback_in_run_log(tmp_path, capsys):
    with pytest.raises(SystemExit) as e, reported("nsd-x") as report, \
            RunFolder(tmp_path, "nsd-x") as folder:
        report.attach(folder)
        [][1]
    assert e.value.code == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "internal error (IndexError" in err and str(tmp_path / LOG_FILE) in err
    assert "Traceback (most recent call last)" in (tmp_path / LOG_FILE).read_text()
