"""The README's set-up command in a fresh clone, a fresh venv and no pip cache (slow: it
installs everything; about 3 minutes where the packages come from a nearby index)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                    reason="needs git and a git checkout")
def test_readme_setup_in_a_fresh_clone(tmp_path):
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True, timeout=300)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("VIRTUAL_ENV", "PYTHON"))}
    env["PIP_NO_CACHE_DIR"] = "1"
    done = subprocess.run(["bash", "tools/setup.sh"], cwd=clone, env=env, capture_output=True,
                          text=True, timeout=1700)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "set-up done: nsd-netepu" in done.stdout
    version = subprocess.run([str(clone / ".venv/bin/nsd-run"), "--version"],
                             capture_output=True, text=True, timeout=120)
    assert version.returncode == 0 and version.stdout.strip().startswith("nsd-run")
    imports = subprocess.run(
        [str(clone / ".venv/bin/python"), "-c",
         "import nsd, netepu, sleap_io, pynwb, ndx_pose, ezc3d, trackeval.metrics; "
         "import cv2; print(cv2.__file__)"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert imports.returncode == 0, imports.stderr[-2000:]
    assert str(clone / ".venv") in imports.stdout  # the venv's own OpenCV, one wheel
