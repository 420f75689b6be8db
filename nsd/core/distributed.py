r"""Data-parallel training with ``torch.distributed`` (launched by ``torchrun``).

``torchrun --nproc_per_node=P -m nsd.cli.train ...`` starts P processes (ranks) and
sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and
``MASTER_PORT`` in each. :func:`init_from_env` joins them into one process
group (``gloo`` on CPU, ``nccl`` when CUDA is available); without those
variables (a plain ``nsd-train``) nothing happens and every function here is a
no-op, so the single-process path is unchanged.

Data parallelism as the :class:`nsd.core.trainer.Trainer` does it:

* every rank builds the same model (same seed) and rank 0's parameters are
  broadcast once more at the start (:func:`broadcast_parameters`), so the
  replicas start identical whatever happened before;
* every rank draws its own batches (its data generator is seeded with
  :func:`rank_seed`), so P ranks see P times the batch per step;
* after ``backward`` the gradients are averaged over the ranks
  (:func:`average_gradients`, one ``all_reduce`` per dtype), so every replica
  takes the same optimiser step and the weights stay identical;
* only rank 0 writes checkpoints, logs and image grids and evaluates.

A task that re-initialises parameters during training (NSD's stage switch)
calls :func:`broadcast_parameters` on them, since the ranks' random streams
differ by design.

Hydra apps (``nsd-train``) run under torchrun through :func:`run_hydra_app`
and take their run directory from :func:`hydra_run_dir`: every rank uses
rank 0's, ranks > 0 write neither ``.hydra/`` nor the log file, so a run has
one output directory and one log whatever the number of ranks.
"""

from __future__ import annotations

import datetime
import logging
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from hydra.core.hydra_config import HydraConfig
from torch import Tensor, nn

__all__ = [
    "RUN_STAMP_ENV",
    "TIMEOUT_ENV",
    "average_gradients",
    "barrier",
    "broadcast_object",
    "broadcast_parameters",
    "gather_objects",
    "hydra_run_dir",
    "init_from_env",
    "is_distributed",
    "rank",
    "rank_seed",
    "run_hydra_app",
    "shutdown",
    "world_size",
]

RUN_STAMP_ENV = "NSD_RUN_STAMP"  # run folder name shared by the ranks (conf/train.yaml)
TIMEOUT_ENV = "NSD_DIST_TIMEOUT_MINUTES"  # collective timeout; ranks wait for rank 0's evaluations
DEFAULT_TIMEOUT_MINUTES = 60.0
_TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def is_distributed() -> bool:
    """True inside an initialised ``torch.distributed`` process group."""
    return dist.is_available() and dist.is_initialized()


def rank() -> int:
    """This process's rank (0 when not distributed)."""
    return dist.get_rank() if is_distributed() else 0


def world_size() -> int:
    """Number of ranks (1 when not distributed)."""
    return dist.get_world_size() if is_distributed() else 1


def init_from_env(backend: str | None = None) -> bool:
    """Join the process group described by torchrun's environment variables.

    Args:
        backend: ``"gloo"`` or ``"nccl"``; default ``nccl`` when CUDA is available,
            else ``gloo``.

    Returns:
        True when this process is now part of a group of more than one rank.

    Raises:
        RuntimeError: when ``WORLD_SIZE > 1`` but another torchrun variable is
            missing (the process was not started by torchrun or a compatible launcher).
    """
    if is_distributed():
        return world_size() > 1
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or not dist.is_available():
        return False
    missing = [k for k in _TORCHRUN_VARS if k not in os.environ]
    if missing:
        raise RuntimeError(
            f"WORLD_SIZE={os.environ['WORLD_SIZE']} but {missing} are not set: start "
            "data-parallel runs with torchrun (see docs/scaling.md)"
        )
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    minutes = float(os.environ.get(TIMEOUT_ENV, DEFAULT_TIMEOUT_MINUTES))
    dist.init_process_group(backend=backend, timeout=datetime.timedelta(minutes=minutes))
    return world_size() > 1


def rank_seed(seed: int, rank_: int | None = None) -> int:
    """The seed of a rank's random streams: ``seed`` on rank 0 (so a one-rank run is
    the single-process run), ``seed + rank * 2**32`` elsewhere (never a user's seed)."""
    r = rank() if rank_ is None else rank_
    return seed + r * 2**32


def _device() -> torch.device:
    if is_distributed() and dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def broadcast_parameters(modules: nn.Module | Iterable[nn.Module], src: int = 0) -> None:
    """Copy the parameters and buffers of ``modules`` from rank ``src`` to every rank."""
    if world_size() <= 1:
        return
    if isinstance(modules, nn.Module):
        modules = [modules]
    with torch.no_grad():
        for m in modules:
            for t in [*m.parameters(), *m.buffers()]:
                if t.device == _device():
                    dist.broadcast(t.data, src)
                else:  # e.g. CPU buffers of a CUDA run
                    tmp = t.data.to(_device())
                    dist.broadcast(tmp, src)
                    t.data.copy_(tmp)


def average_gradients(params: Sequence[Tensor], extra: Tensor | None = None) -> Tensor | None:
    """Average ``.grad`` of ``params`` (and ``extra``) over the ranks, in place.

    A parameter whose gradient is None on some ranks is treated as zero there;
    it stays None only where no rank has a gradient, so optimisers that skip
    parameters without gradients (Adam) do the same thing on every rank.

    Args:
        params: the parameters, in the same order on every rank.
        extra: a float vector to average along (loss terms, ...), or None.

    Returns:
        The averaged ``extra`` (float64), or None.
    """
    n = world_size()
    if n <= 1:
        return extra
    device = _device()
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.float64, device=device)
    head = [has] if extra is None else [has, extra.detach().to(device, torch.float64).flatten()]
    small = torch.cat(head)
    dist.all_reduce(small)
    any_grad = small[: len(params)] > 0
    by_dtype: dict[torch.dtype, list[Tensor]] = {}
    for p, flag in zip(params, any_grad.tolist(), strict=True):
        if not flag:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        by_dtype.setdefault(p.grad.dtype, []).append(p)
    for group in by_dtype.values():
        flat = torch.cat([p.grad.reshape(-1).to(device) for p in group])
        dist.all_reduce(flat)
        flat /= n
        offset = 0
        for p in group:
            k = p.grad.numel()
            p.grad.copy_(flat[offset : offset + k].view_as(p.grad))
            offset += k
    return None if extra is None else small[len(params) :] / n


def broadcast_object(obj: Any, src: int = 0) -> Any:
    """Rank ``src``'s ``obj`` on every rank (picklable objects)."""
    if world_size() <= 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src, device=_device())
    return box[0]


def gather_objects(obj: Any, dst: int = 0) -> list[Any] | None:
    """Every rank's ``obj`` as a list on rank ``dst`` (None elsewhere); ``[obj]`` alone."""
    if world_size() <= 1:
        return [obj]
    out: list[Any] | None = [None] * world_size() if rank() == dst else None
    dist.gather_object(obj, out, dst=dst)
    return out


def barrier() -> None:
    """Wait for every rank (no-op when not distributed)."""
    if world_size() > 1:
        if dist.get_backend() == "nccl":
            dist.barrier(device_ids=[torch.cuda.current_device()])
        else:
            dist.barrier()


def shutdown() -> None:
    """Leave the process group (no-op when not distributed)."""
    if is_distributed():
        dist.destroy_process_group()


def run_hydra_app(app: Callable[[], Any]) -> Any:
    """Run a ``@hydra.main`` function, under torchrun as one rank of its process group.

    Before Hydra starts, the ranks join their group and agree on rank 0's start
    time, exported as ``NSD_RUN_STAMP`` (``conf/train.yaml`` names the run folder
    after it, so every rank resolves the same folder); ranks > 0 get
    ``hydra.output_subdir=null`` (no second ``.hydra/``). Without torchrun it just
    calls ``app()``.
    """
    if init_from_env():
        os.environ[RUN_STAMP_ENV] = broadcast_object(time.strftime("%Y-%m-%d_%H-%M-%S"))
        if rank() > 0 and not any(a.startswith("hydra.output_subdir=") for a in sys.argv[1:]):
            sys.argv.append("hydra.output_subdir=null")
    try:
        return app()
    finally:
        shutdown()


def hydra_run_dir() -> Path:
    """The running Hydra job's output directory; rank 0's on every rank.

    Ranks > 0 also stop writing the job's log file and drop to WARNING, so that
    the run's log is rank 0's alone.
    """

    if rank() > 0:
        root = logging.getLogger()
        for h in list(root.handlers):
            if isinstance(h, logging.FileHandler):
                root.removeHandler(h)
                h.close()
        root.setLevel(logging.WARNING)
    return Path(broadcast_object(HydraConfig.get().runtime.output_dir))
