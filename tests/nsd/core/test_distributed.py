"""Data-parallel training on 2 CPU processes (gloo): identical replicas, one run folder.

The fast test spawns 2 ranks that train the tiny NSD config of
``test_nsd_train.py`` through :class:`nsd.core.trainer.Trainer` (straight, and
stopped + resumed); the slow one runs ``torchrun -m nsd.cli.train`` end to end.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from nsd.core import distributed
from nsd.core.trainer import load_checkpoint
from tests.conftest import FIXTURES

STEPS = 4


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, scene: str, root: str) -> None:
    """One rank: train straight to STEPS in a/, and to STEPS // 2 then resumed in b/."""
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world),
        LOCAL_RANK=str(rank),
        NSD_DIST_TIMEOUT_MINUTES="3",  # a hang fails the test instead of blocking CI
    )
    torch.set_num_threads(1)
    from nsd.core.trainer import Trainer, TrainerConfig, seed_everything
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask
    from tests.nsd.training.test_train import tiny_cfg

    assert distributed.init_from_env()
    try:
        cfg = tiny_cfg()
        data = SceneData(Path(scene), (32, 24), val_fraction=0.25)
        seen: list[float] = []
        sample = data.sample

        def recording_sample(rng, n, **kwargs):
            batch = sample(rng, n, **kwargs)
            seen.append(float(batch.image_v.sum()))
            return batch

        data.sample = recording_sample
        out = {}
        for name, steps in (("a", STEPS), ("b", STEPS // 2), ("b", STEPS)):
            seed_everything(3)  # model initialisation, as nsd.training.train.train does
            task = NSDTask(cfg, data)
            init = {k: v.clone() for k, v in task.model.state_dict().items()}
            tc = TrainerConfig.defaults(max_steps=steps, log_every=1, checkpoint_every=2,
                                        progress=False, seed=3)
            metrics = Trainer(task, tc, Path(root) / name).fit()
            out[f"{name}{steps}"] = {"init": init, "final": task.model.state_dict(),
                                     "metrics": metrics}
        out["batches"] = seen
        torch.save(out, Path(root) / f"rank{rank}.pt")
    finally:
        distributed.shutdown()


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    scene = root / "tiny_scene"  # a copy: the background cache must not touch the fixture
    shutil.copytree(FIXTURES / "tiny_scene", scene)
    mp.spawn(_worker, args=(2, _free_port(), str(scene), str(root)), nprocs=2, join=True)
    return root, [torch.load(root / f"rank{r}.pt", weights_only=False) for r in range(2)]


def test_ranks_hold_identical_trained_weights(two_ranks):
    _, (r0, r1) = two_ranks
    a0, a1 = r0[f"a{STEPS}"], r1[f"a{STEPS}"]
    for k in a0["final"]:
        assert torch.equal(a0["final"][k], a1["final"][k]), k
        assert torch.equal(a0["init"][k], a1["init"][k]), k
    assert any(not torch.equal(a0["final"][k], a0["init"][k]) for k in a0["final"])
    # every rank drew its own batches (else data parallelism would repeat the data)
    assert r0["batches"][:STEPS] != r1["batches"][:STEPS]
    # every rank returns rank 0's evaluation
    assert a0["metrics"] and a0["metrics"] == a1["metrics"]


def test_resume_with_the_same_ranks_is_exact(two_ranks):
    _, (r0, r1) = two_ranks
    for r in (r0, r1):
        for k, v in r[f"a{STEPS}"]["final"].items():
            assert torch.equal(v, r[f"b{STEPS}"]["final"][k]), k


def test_one_run_folder_written_by_rank_zero(two_ranks):
    root, _ = two_ranks
    run = root / "a"
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "grids", "metrics.csv", "tb"]
    assert len(list((run / "tb").iterdir())) == 1  # one TensorBoard writer
    lines = (run / "metrics.csv").read_text().splitlines()
    steps = [row.split(",")[0] for row in lines[1:]]
    # one row per logged step (train) plus the final evaluation, no rank writes twice
    assert steps == [str(s) for s in range(1, STEPS + 1)] + [str(STEPS)]
    state = load_checkpoint(run / "checkpoint.pt")
    ranks = state["rng_ranks"]
    assert len(ranks) == 2
    assert ranks[0]["numpy_generator"] != ranks[1]["numpy_generator"]
    assert ranks[0]["numpy_generator"] == state["rng"]["numpy_generator"]


def test_not_distributed_is_a_no_op(tmp_path, monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert distributed.init_from_env() is False
    assert (distributed.rank(), distributed.world_size()) == (0, 1)
    assert distributed.rank_seed(7) == 7
    assert distributed.broadcast_object({"x": 1}) == {"x": 1}
    assert distributed.gather_objects(3) == [3]
    p = torch.nn.Parameter(torch.ones(2))
    p.grad = torch.full((2,), 3.0)
    extra = torch.tensor([1.5])
    assert distributed.average_gradients([p], extra) is extra
    assert torch.equal(p.grad, torch.full((2,), 3.0))


def test_world_size_without_torchrun_variables_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    for k in ("RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    with pytest.raises(RuntimeError, match="start data-parallel runs with torchrun"):
        distributed.init_from_env()


@pytest.mark.slow
def test_torchrun_nsd_train_writes_one_run_directory(tmp_path):
    """``torchrun --nproc_per_node=2 -m nsd.cli.train``: one run folder, one log, one .hydra."""
    from tests.nsd.training.test_train import TINY

    scene = tmp_path / "tiny_scene"
    shutil.copytree(FIXTURES / "tiny_scene", scene)
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
        "-m", "nsd.cli.train", *TINY, f"data.scene={scene}", "trainer.max_steps=3",
        "trainer.log_every=1", "trainer.progress=false",
    ]
    env = {**os.environ, "NSD_DIST_TIMEOUT_MINUTES": "3"}
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    runs = list((tmp_path / "runs" / "nsd").iterdir())
    assert len(runs) == 1, runs
    run = runs[0]
    assert {".hydra", "checkpoint.pt", "metrics.csv", "tb", "train.log"} <= {
        p.name for p in run.iterdir()
    }
    assert len(list((run / "tb").iterdir())) == 1
    assert (run / "train.log").read_text().count("final metrics") == 1
    assert len(load_checkpoint(run / "checkpoint.pt")["rng_ranks"]) == 2
