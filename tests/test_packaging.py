"""Packaging: every package is listed, no top-level `datasets`, configs load from a wheel."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_package_is_listed():
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    found = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("nsd", "netepu")
        for p in (ROOT / top).rglob("__init__.py")
    }
    found.add("nsd.conf")
    assert listed == found, (
        f"pyproject.toml packages differ: missing {found - listed}, extra {listed - found}"
    )
    assert not any(p.split(".")[0] == "datasets" for p in listed)


def test_top_level_layout():
    expected = {
        "nsd",
        "netepu",
        "conf",
        "datasets",
        "tools",
        "tests",
        "pyproject.toml",
        "README.md",
    }
    allowed_extra = {
        ".ci",
        "docs",
        "LICENSE",
        "CITATION.cff",
        ".gitignore",
        ".git",
        ".venv",
        ".cache",
        ".pytest_cache",
        ".ruff_cache",
        ".hypothesis",
        "outputs",
        "multirun",
        "runs",
        "scenes",
        "nsd_netepu.egg-info",
        "build",
        "dist",
    }
    present = {p.name for p in ROOT.iterdir()}
    assert expected <= present
    assert present - expected - allowed_extra == set(), present - expected - allowed_extra


def test_ci_runs_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    cmd = "bash tools/setup.sh --dev && .venv/bin/python -m pytest"
    assert cmd in readme and cmd in ci


@pytest.mark.skipif(sys.prefix == sys.base_prefix, reason="needs to run inside a virtualenv")
def test_wheel_install_finds_hydra_configs(tmp_path):
    """`pip install .` (a wheel, not editable) into a fresh venv loads every Hydra config."""
    wheel_dir = tmp_path / "wheel"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(wheel_dir),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    wheel = next(wheel_dir.glob("*.whl"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run(
        [py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    # install the wheel into the fresh venv with this interpreter's pip
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", site, str(wheel)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    # dependencies (hydra, omegaconf, ...) from this environment, *after* the venv's own
    # site-packages, as a plain path (so this checkout's editable finder is not loaded)
    Path(site, "zz_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    assert not (Path(site) / "datasets").exists()
    script = (
        "import nsd, nsd.conf, pathlib, importlib.resources as r\n"
        f"assert not nsd.__file__.startswith({str(ROOT)!r}), nsd.__file__\n"
        "from hydra import compose, initialize_config_module\n"
        "names = sorted(p.name[:-5] for p in r.files('nsd.conf').iterdir()\n"
        "               if p.name.endswith('.yaml'))\n"
        "assert names, 'no configs shipped'\n"
        "with initialize_config_module('nsd.conf', version_base='1.3'):\n"
        "    for n in names:\n"
        "        compose(n)\n"
        "print(' '.join(names))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([py, "-c", script], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip()


def test_citation_names_both_papers_and_the_version():
    import nsd

    text = (ROOT / "CITATION.cff").read_text()
    assert f"version: {nsd.__version__}\n" in text
    assert "Neural Scene Decomposition for Multi-Person Motion Capture" in text
    assert "Neural Texture Puppeteer" in text
    assert (ROOT / "LICENSE").read_text().startswith("BSD 3-Clause License")


def test_every_command_prints_its_version():
    import nsd

    for script in ("nsd-run", "nsd-train", "nsd-check"):
        res = subprocess.run([str(Path(sys.executable).parent / script), "--version"],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0 and res.stdout.strip() == (
            f"{script} (nsd-netepu) {nsd.__version__}"), res
