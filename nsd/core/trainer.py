"""One trainer machinery for every model of the toolkit (NSD stages, NeTePu stages).

A *task* holds the models, the optimisers and the data and knows how to take
one training step; the :class:`Trainer` owns the loop: seeding, progress bar
with ETA, TensorBoard and CSV logs, periodic evaluation and image grids,
gradient clipping, atomic checkpoints and exact resume (models, optimisers,
schedulers, every random number generator and the step counter), and budgets
in steps or in minutes of training time (evaluation time is not counted).

Exact resume: with the same config, a run stopped at step k and resumed
produces bit-for-bit the same weights as a run that never stopped, because
the data sampler draws from a ``numpy.random.Generator`` whose state is saved,
torch's global RNG (dropout) is saved, and no worker processes are used.

Data parallelism (:mod:`nsd.core.distributed`): under ``torchrun`` every rank runs
this loop on its own batches (its random streams seeded with
:func:`nsd.core.distributed.rank_seed`); gradients are averaged over the ranks
after ``backward`` (together with the loss terms, which are logged and checked
as averages), rank 0's parameters are broadcast at the start, and rank 0's
training clock decides the minute budgets for everyone. Only rank 0 writes
the checkpoint (with every rank's random state, so resume with the same number
of ranks is exact), logs, grids and evaluates; the others wait for it at the
next collective. With one process nothing of this runs.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import pickle
import random
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import cv2
import numpy as np
import torch
from torch import nn
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from nsd.core import distributed
from nsd.core.atomic import atomic_save_torch
from nsd.core.config import ConfigSection
from nsd.core.device import move
from nsd.core.errors import CheckpointError, ConfigError, NonFiniteError

__all__ = [
    "CHECKPOINT_FORMAT",
    "TrainTask",
    "Trainer",
    "TrainerConfig",
    "is_main_process",
    "load_checkpoint",
    "seed_everything",
]

CHECKPOINT_FORMAT = "nsd-netepu-checkpoint-v1"  # the tag every checkpoint of the toolkit carries


log = logging.getLogger(__name__)

def seed_everything(seed: int) -> np.random.Generator:
    """Seed python, numpy and torch; return the data generator for the task."""
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 (third-party code may use the global RNG)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


def is_main_process() -> bool:
    """True unless this is a non-zero rank of a ``torch.distributed`` job."""
    return not (torch.distributed.is_available() and torch.distributed.is_initialized()) or (
        torch.distributed.get_rank() == 0
    )


class TrainTask(Protocol):
    """What the :class:`Trainer` needs from a model + data + losses bundle.

    Optional members the trainer uses when present: ``schedulers()``,
    ``extra_state()`` / ``load_extra_state(state)`` (saved in the checkpoint) and
    ``finish(step)`` (called once after the last step, before the final checkpoint).
    """

    def modules(self) -> Mapping[str, nn.Module]:
        """Every module whose weights go into the checkpoint."""

    def optimizers(self) -> Mapping[str, torch.optim.Optimizer]:
        """Optimisers (stepped by the trainer after ``training_step``)."""

    def training_step(self, step: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
        """Sample a batch with ``rng``, return the loss terms; ``"loss"`` is minimised."""

    def evaluate(self, step: int) -> dict[str, float]:
        """Validation metrics (no gradients)."""

    def image_grids(self, step: int) -> dict[str, np.ndarray]:
        """Images for a person to look at: name -> uint8 (H, W, 3)."""


@dataclass
class TrainerConfig(ConfigSection):
    """Settings of the training loop (every field is a Hydra config value)."""

    APP: ClassVar[str] = "train"  # defaults: conf/train.yaml, section `trainer`
    KEY: ClassVar[str] = "trainer"

    max_steps: int  # stop after this many steps (<= 0: no step limit)
    max_minutes: float  # stop after this much training time (<= 0: no limit)
    eval_at_minutes: list[float]  # extra evals at these times
    log_every: int  # steps between scalar logs
    eval_every: int  # steps between evaluations (0: only at the end)
    grid_every: int  # steps between image grids (0: only at the end)
    checkpoint_every: int  # steps between checkpoints (0: only at the end)
    grad_clip: float  # max gradient norm per optimiser (0: no clipping)
    seed: int
    resume: bool  # continue from <out_dir>/checkpoint.pt when it exists
    progress: bool  # tqdm progress bar
    detect_anomaly: bool  # torch.autograd anomaly detection (slow)
    stop_on_nonfinite: bool  # raise with a clear message on a NaN/Inf loss or gradient

    def validate(self) -> None:
        if self.max_steps <= 0 and self.max_minutes <= 0:
            raise ConfigError("trainer: set max_steps > 0 or max_minutes > 0, else it never stops")
        for k in ("log_every", "eval_every", "grid_every", "checkpoint_every"):
            if getattr(self, k) < 0:
                raise ConfigError(f"trainer.{k} must be >= 0, got {getattr(self, k)}")
        if self.grad_clip < 0:
            raise ConfigError(f"trainer.grad_clip must be >= 0, got {self.grad_clip}")


def _rng_state(rng: np.random.Generator) -> dict[str, Any]:
    legacy = np.random.get_state(legacy=False)  # noqa: NPY002
    # plain types only, so that checkpoints load with weights_only=True
    legacy["state"] = {
        "key": torch.from_numpy(legacy["state"]["key"].astype(np.int64)),
        "pos": int(legacy["state"]["pos"]),
    }
    return {
        "numpy_generator": rng.bit_generator.state,
        "numpy_global": legacy,
        "python": random.getstate(),
        "torch": torch.get_rng_state(),
        "torch_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def _set_rng_state(rng: np.random.Generator, state: Mapping[str, Any]) -> None:
    rng.bit_generator.state = state["numpy_generator"]
    legacy = dict(state["numpy_global"])
    legacy["state"] = {
        "key": legacy["state"]["key"].numpy().astype(np.uint32),
        "pos": legacy["state"]["pos"],
    }
    np.random.set_state(legacy)  # noqa: NPY002
    random.setstate(state["python"])
    torch.set_rng_state(state["torch"])
    cuda = state.get("torch_cuda", [])
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``; clear errors when it is unusable.

    Raises:
        CheckpointError: missing, not a torch file, a pickle that would run code (refused,
            never retried without ``weights_only``), or not a mapping.
    """
    path = Path(path)
    if path.is_dir() and (path / "checkpoint.pt").is_file():
        path = path / "checkpoint.pt"
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        with warnings.catch_warnings():  # torch's note on pickle protocols is not for users
            warnings.simplefilter("ignore", UserWarning)
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if "Weights only load failed" in str(e):
            raise CheckpointError(
                f"checkpoint {path} holds objects other than tensors and plain data; it was "
                "refused because loading it could run code. Use a checkpoint written by "
                "nsd-train or netepu-train") from None
        raise CheckpointError(f"checkpoint {path} is not a torch checkpoint file") from None
    except Exception:  # a text file, a truncated download, another format
        raise CheckpointError(f"checkpoint {path} is not a torch checkpoint file (corrupt, "
                              "truncated or another format)") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(state).__name__}, not a "
                              "checkpoint of this toolkit (nsd-train or netepu-train)")
    return state


class CsvLog:
    """Append-only CSV of scalars; a new column rewrites the header."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.columns: list[str] = []
        if path.is_file():
            with path.open() as f:
                header = f.readline().strip()
            self.columns = header.split(",") if header else []

    def write(self, row: Mapping[str, float]) -> None:
        new = [k for k in row if k not in self.columns]
        if new:
            rows = []
            if self.path.is_file():
                with self.path.open() as f:
                    rows = list(csv.DictReader(f))
            self.columns += new
            with self.path.open("w", newline="") as f:
                w = csv.DictWriter(f, self.columns)
                w.writeheader()
                w.writerows(rows)
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.columns).writerow(dict(row))


class Trainer:
    """The training loop shared by every task.

    Args:
        task: a :class:`TrainTask`.
        cfg: loop settings.
        out_dir: run folder: ``checkpoint.pt``, ``metrics.csv``, ``tb/``, ``grids/``.
        config: the run's full config (stored in the checkpoint for provenance).
        on_eval: called with (step, train_minutes, metrics) after every evaluation.
    """

    def __init__(
        self,
        task: TrainTask,
        cfg: TrainerConfig,
        out_dir: str | os.PathLike,
        config: Mapping[str, Any] | None = None,
        on_eval: Callable[[int, float, dict[str, float]], None] | None = None,
    ) -> None:
        cfg.validate()
        self.task, self.cfg = task, cfg
        self.out_dir = Path(out_dir)
        self.config = dict(config or {})
        self.on_eval = on_eval
        self.rank, self.world = distributed.rank(), distributed.world_size()
        self.rng = seed_everything(distributed.rank_seed(cfg.seed))
        self.step = 0
        self.train_seconds = 0.0  # the budget clock (rank 0's, shared by every rank)
        self._own_seconds = 0.0  # rank 0's own clock under torch.distributed
        self._shared_clock = 0.0  # rank 0's clock as of the last gradient synchronisation
        self.main = is_main_process()
        self._tb = None
        self._csv: CsvLog | None = None
        self._evals_done: set[float] = set()
        self.history: list[dict[str, float]] = []
        self._names: dict[int, str] | None = None

    # ------------------------------------------------------------------ state
    @property
    def checkpoint_path(self) -> Path:
        return self.out_dir / "checkpoint.pt"

    def state_dict(self) -> dict[str, Any]:
        task_extra = getattr(self.task, "extra_state", None)
        schedulers = getattr(self.task, "schedulers", lambda: {})()
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "train_seconds": self.train_seconds,
            "evals_done": sorted(self._evals_done),
            # CPU tensors: a checkpoint written on a GPU loads on any machine
            "modules": {k: move(m.state_dict(), "cpu") for k, m in self.task.modules().items()},
            "optimizers": {k: move(o.state_dict(), "cpu")
                           for k, o in self.task.optimizers().items()},
            "schedulers": {k: s.state_dict() for k, s in schedulers.items()},
            "rng": _rng_state(self.rng),
            "task": task_extra() if task_extra else {},
            "config": self.config,
        }

    def save(self) -> None:
        """Write the checkpoint (rank 0); under torch.distributed every rank must call it."""
        ranks = distributed.gather_objects(_rng_state(self.rng)) if self.world > 1 else None
        if self.main:
            state = self.state_dict()
            if ranks is not None:
                state["rng_ranks"] = ranks
            atomic_save_torch(state, self.checkpoint_path)

    def load(self, path: str | os.PathLike) -> None:
        state = load_checkpoint(path)
        if state.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointError(f"{path} is not a checkpoint of this toolkit")
        modules = self.task.modules()
        missing = sorted(set(modules) - set(state["modules"]))
        if missing:
            raise CheckpointError(f"{path} lacks the modules {missing}")
        for k, m in modules.items():
            try:
                m.load_state_dict(state["modules"][k])
            except RuntimeError as e:
                raise CheckpointError(f"{path}: module '{k}' does not match the config: {e}") from e
        for k, o in self.task.optimizers().items():
            if k in state["optimizers"]:
                o.load_state_dict(state["optimizers"][k])
        for k, s in getattr(self.task, "schedulers", lambda: {})().items():
            if k in state.get("schedulers", {}):
                s.load_state_dict(state["schedulers"][k])
        if hasattr(self.task, "load_extra_state"):
            self.task.load_extra_state(state.get("task", {}))
        self.step = int(state["step"])
        self.train_seconds = self._own_seconds = float(state["train_seconds"])
        self._evals_done = set(state.get("evals_done", []))
        ranks = state.get("rng_ranks")
        if self.world == 1 or self.rank == 0:
            _set_rng_state(self.rng, state["rng"])  # rank 0's state
        elif ranks is not None and len(ranks) == self.world:
            _set_rng_state(self.rng, ranks[self.rank])
        else:  # saved by a different number of ranks: fresh streams, not bit-exact
            self.rng = seed_everything(distributed.rank_seed(self.cfg.seed) + self.step)

    # ------------------------------------------------------------------ logging
    def _log(self, scalars: Mapping[str, float], prefix: str) -> None:
        if not self.main:
            return
        if self._tb is None:
            self._tb = SummaryWriter(str(self.out_dir / "tb"))
            self._csv = CsvLog(self.out_dir / "metrics.csv")
        for k, v in scalars.items():
            self._tb.add_scalar(f"{prefix}/{k}", v, self.step)
        self._csv.write(
            {
                "step": self.step,
                "minutes": round(self.train_seconds / 60, 4),
                **{f"{prefix}/{k}": v for k, v in scalars.items()},
            }
        )

    def _grids(self) -> None:
        if not self.main:
            return

        with torch.random.fork_rng(devices=[]):
            grids = self.task.image_grids(self.step)
        folder = self.out_dir / "grids"
        folder.mkdir(parents=True, exist_ok=True)
        for name, img in grids.items():
            cv2.imwrite(
                str(folder / f"{name}_{self.step:07d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
            )
            if self._tb is not None:
                self._tb.add_image(name, img, self.step, dataformats="HWC")

    def _evaluate(self) -> dict[str, float]:
        if not self.main:  # rank 0 evaluates; the others wait for it at the next collective
            return {}
        # evaluation must not consume the training RNGs (exact resume, eval-schedule-free)
        with torch.random.fork_rng(devices=[]):
            metrics = self.task.evaluate(self.step)
        metrics = {k: float(v) for k, v in metrics.items()}
        self._log(metrics, "eval")
        row = {"step": self.step, "minutes": self.train_seconds / 60, **metrics}
        self.history.append(row)
        if self.on_eval:
            self.on_eval(self.step, self.train_seconds / 60, metrics)
        return metrics

    # ------------------------------------------------------------------ loop
    def _done(self) -> bool:
        c = self.cfg
        return (c.max_steps > 0 and self.step >= c.max_steps) or (
            c.max_minutes > 0 and self.train_seconds >= 60 * c.max_minutes
        )

    def _check_losses(self, losses: Mapping[str, torch.Tensor]) -> None:
        """Stop before ``backward()`` on a non-finite loss, naming the terms."""
        bad = [k for k, v in losses.items() if not torch.isfinite(v).all()]
        if bad:
            where = f" (averaged over {self.world} ranks)" if self.world > 1 else ""
            raise NonFiniteError(
                f"step {self.step}: non-finite loss terms {bad}{where}; lower the learning rate or "
                "the prior weights, or enable trainer.detect_anomaly to find the operation"
            )

    def _named_parameters(self) -> dict[int, str]:
        if self._names is None:
            self._names = {id(p): f"{m}.{n}" for m, mod in self.task.modules().items()
                           for n, p in mod.named_parameters()}
        return self._names

    def _check_tensors(self, what: str, advice: str) -> None:
        """Stop on a non-finite gradient (``what='gradient'``) or parameter, naming the
        optimiser, its parameter group and the parameter."""
        for name, opt in self.task.optimizers().items():
            for i, g in enumerate(opt.param_groups):
                for p in g["params"]:
                    t = p.grad if what == "gradient" else p
                    if t is not None and not torch.isfinite(t).all():
                        param = self._named_parameters().get(id(p), "?")
                        raise NonFiniteError(
                            f"step {self.step}: non-finite {what} of parameter '{param}' "
                            f"(optimiser '{name}', parameter group {i}, learning rate "
                            f"{g.get('lr')}); {advice}")

    def _synchronise(self, losses: Mapping[str, torch.Tensor], t0: float) -> dict[str, Any]:
        """Average gradients and loss terms over the ranks; share rank 0's clock."""
        names = sorted(losses)
        clock = self._own_seconds + time.perf_counter() - t0 if self.main else 0.0
        extra = torch.stack(
            [*(torch.as_tensor(losses[k]).detach().double().reshape(()).cpu() for k in names),
             torch.tensor(clock, dtype=torch.float64)]
        )
        params = {id(p): p for o in self.task.optimizers().values()
                  for g in o.param_groups for p in g["params"]}
        mean = distributed.average_gradients(list(params.values()), extra)
        self._shared_clock = float(mean[-1]) * self.world  # only rank 0 contributed
        return {k: mean[i].cpu() for i, k in enumerate(names)}

    def fit(self) -> dict[str, float]:
        """Train until the budget is spent; returns the final evaluation metrics.

        Under torch.distributed every rank calls it and gets rank 0's metrics.
        """
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if self._should_resume():
            self.load(self.checkpoint_path)
            log.info("resumed from %s at step %d (%.1f training minutes)",
                     self.checkpoint_path, self.step, self.train_seconds / 60)
        if self.cfg.stop_on_nonfinite:  # e.g. a checkpoint that holds NaN weights
            self._check_tensors("value", "the run starts from non-finite weights: "
                                         "give another checkpoint or init_from")
        distributed.broadcast_parameters(self.task.modules().values())
        for m in self.task.modules().values():
            m.train()
        bar = None
        if self.cfg.progress and self.main:
            total = self.cfg.max_steps if self.cfg.max_steps > 0 else None
            bar = tqdm(total=total, initial=self.step, desc="train", dynamic_ncols=True, unit="it")
        minute_marks = sorted(m for m in self.cfg.eval_at_minutes if m not in self._evals_done)
        ctx = torch.autograd.set_detect_anomaly(True) if self.cfg.detect_anomaly else None
        if ctx is not None:
            ctx.__enter__()
        try:
            while not self._done():
                losses = self._step()
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(
                        loss=f"{losses['loss'].item():.4f}", min=f"{self.train_seconds / 60:.1f}"
                    )
                self._after_step(losses, minute_marks)
        finally:
            if ctx is not None:
                ctx.__exit__(None, None, None)
            if bar is not None:
                bar.close()
        finish = getattr(self.task, "finish", None)
        if finish is not None:  # optional: work after the last step that the checkpoint keeps
            finish(self.step)
        self.save()
        metrics = self._evaluate()
        self._grids()
        if self._tb is not None:
            self._tb.flush()
        return distributed.broadcast_object(metrics)

    def _should_resume(self) -> bool:
        """Resume from the run's checkpoint? Rank 0 decides for every rank."""
        resume = self.cfg.resume and self.checkpoint_path.is_file()
        if self.world > 1:
            decided = distributed.broadcast_object(resume)
            if decided and not resume:
                raise CheckpointError(
                    f"rank {self.rank} cannot read {self.checkpoint_path}, which rank 0 resumes "
                    "from: put the run directory on a filesystem that every node shares"
                )
            resume = decided
        return resume

    def _step(self) -> dict[str, torch.Tensor]:
        """One optimisation step of every optimiser; returns the step's losses."""
        t0 = time.perf_counter()
        opts = self.task.optimizers()
        for o in opts.values():
            o.zero_grad(set_to_none=True)
        losses = self.task.training_step(self.step, self.rng)
        guard = self.cfg.stop_on_nonfinite
        if guard and self.world == 1:
            self._check_losses(losses)  # before any backward pass on non-finite values
        losses["loss"].backward()
        if self.world > 1:
            losses = self._synchronise(losses, t0)
            if guard:  # every rank sees the same averages and stops together
                self._check_losses(losses)
        if guard:
            self._check_tensors("gradient", "enable trainer.grad_clip or lower the learning rate")
        if self.cfg.grad_clip > 0:
            for o in opts.values():
                params = [p for g in o.param_groups for p in g["params"]]
                torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)
        for o in opts.values():
            o.step()
        if guard:
            self._check_tensors("value", "lower the learning rate or enable trainer.grad_clip")
        for s in getattr(self.task, "schedulers", lambda: {})().values():
            s.step()
        self.step += 1
        if self.world > 1:
            self._own_seconds += time.perf_counter() - t0
            self.train_seconds = self._shared_clock
        else:
            self.train_seconds += time.perf_counter() - t0
        return losses

    def _after_step(self, losses: dict[str, torch.Tensor], minute_marks: list[float]) -> None:
        """Logs, evaluations (at steps and at training minutes), grids and checkpoints due."""
        c = self.cfg
        if c.log_every and self.step % c.log_every == 0:
            self._log({k: v.item() for k, v in losses.items()}, "train")
        while minute_marks and self.train_seconds >= 60 * minute_marks[0]:
            self._evaluate()
            self._evals_done.add(minute_marks.pop(0))
        if c.eval_every and self.step % c.eval_every == 0:
            self._evaluate()
        if c.grid_every and self.step % c.grid_every == 0:
            self._grids()
        if c.checkpoint_every and self.step % c.checkpoint_every == 0:
            self.save()

    def throughput(self) -> float:
        """Training iterations per second so far."""
        return self.step / self.train_seconds if self.train_seconds > 0 else math.nan
