"""Hydra launchers for sweeps: the shipped SLURM config composes; a joblib sweep runs."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_module

from tests.conftest import FIXTURES

HAS_SUBMITIT = importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is not None


@pytest.mark.skipif(
    not HAS_SUBMITIT,
    reason="hydra-submitit-launcher is not installed (optional: pip install 'nsd-netepu[slurm]')",
)
def test_slurm_launcher_config_composes():
    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose(
            "train",
            overrides=["hydra/launcher=slurm_cpu", "hydra.launcher.partition=short"],
            return_hydra_config=True,
        )
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    # our values override the plugin's defaults; the command line overrides ours
    assert (launcher.partition, launcher.timeout_min, launcher.cpus_per_task) == ("short", 120, 2)
    assert launcher.gpus_per_node == 0 and launcher.max_num_timeout == 3
    assert launcher.submitit_folder.endswith(".submitit/%j")


def test_joblib_launcher_is_a_core_dependency():
    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose("train", overrides=["hydra/launcher=joblib"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher")


@pytest.mark.slow
def test_joblib_sweep_over_a_prior_weight(tmp_path):
    """``nsd-train -m prior_position.weight=0,0.1 hydra/launcher=joblib``: both jobs train."""
    from tests.nsd.training.test_train import TINY

    scene = tmp_path / "tiny_scene"
    shutil.copytree(FIXTURES / "tiny_scene", scene)
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable, "-m", "nsd.cli.train", "-m", "prior_position.weight=0,0.1",
        "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}",
        *TINY, f"data.scene={scene}", "trainer.max_steps=3", "trainer.progress=false",
    ]
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (sweep / "multirun.yaml").is_file()
    for job, weight in (("0", "0"), ("1", "0.1")):
        run = sweep / job
        assert (run / "checkpoint.pt").is_file() and (run / "metrics.csv").is_file()
        overrides = (run / ".hydra" / "overrides.yaml").read_text()
        assert f"prior_position.weight={weight}" in overrides
