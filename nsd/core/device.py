"""Which device torch computes on: the ``device`` setting of every command.

``device: auto`` (the default) takes the CUDA GPU when this torch build has one
available and the CPU otherwise; ``cpu``, ``cuda`` and ``cuda:N`` are used as given,
with a clear error when the machine cannot honour them. Under torchrun, ``auto`` and
``cuda`` take the GPU of the process's ``LOCAL_RANK``. Apple's ``mps`` is accepted
when asked for by name, never picked by ``auto`` (some operators the models use fall
back to the CPU there).

The models, their batches and every tensor they create live on this device; numpy
work (the visual hull, matching, files) stays on the CPU and its results are moved
once per batch. Checkpoints are always written and read as CPU tensors, so a model
trained on a GPU loads on a laptop and the other way round.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import re
from collections.abc import Iterator
from typing import Any

import torch

from nsd.core.errors import ConfigError

__all__ = ["DEVICE_PATTERN", "call_on_device", "model_device", "move", "on_cpu", "resolve_device"]

DEVICE_PATTERN = re.compile(r"^(auto|cpu|mps|cuda(:\d+)?)$")  # the values a `device` key takes


def resolve_device(setting: str, key: str = "device") -> torch.device:
    """The torch device a ``device`` setting names on this machine.

    Args:
        setting: ``auto``, ``cpu``, ``cuda``, ``cuda:N`` or ``mps``.
        key: the config key, named in errors.

    Raises:
        ConfigError: for an unknown value, or a GPU this machine or torch build lacks.

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    value = str(setting).strip().lower()
    if not DEVICE_PATTERN.match(value):
        raise ConfigError(f"{key}={setting!r}: use auto, cpu, cuda, cuda:N or mps")
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if value == "auto":
        return torch.device("cuda", local) if torch.cuda.is_available() else torch.device("cpu")
    if value == "cpu":
        return torch.device("cpu")
    if value == "mps":
        if not torch.backends.mps.is_available():
            raise ConfigError(f"{key}=mps: this machine or torch build has no MPS; use {key}=auto")
        return torch.device("mps")
    if not torch.cuda.is_available():
        raise ConfigError(
            f"{key}={setting}: torch {torch.__version__} sees no CUDA GPU on this machine; "
            f"use {key}=auto or {key}=cpu (a CUDA build of torch and a driver are needed)"
        )
    index = int(value.split(":")[1]) if ":" in value else local
    if index >= torch.cuda.device_count():
        raise ConfigError(
            f"{key}={setting}: this machine has {torch.cuda.device_count()} CUDA device(s) "
            f"(0 to {torch.cuda.device_count() - 1})"
        )
    return torch.device("cuda", index)


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of a model's parameters (the CPU for a model without any)."""
    first = next(model.parameters(), None)
    return torch.device("cpu") if first is None else first.device


def move(value: Any, device: torch.device | str) -> Any:
    """``value`` with every tensor in it on ``device``: tensors, dataclasses (a new
    instance of the same class), named tuples, lists, tuples and dicts, recursively;
    anything else as it is.

    Example:
        >>> move({"x": torch.zeros(2), "n": 3}, "cpu")["x"].device
        device(type='cpu')
    """
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        moved = {
            f.name: move(getattr(value, f.name), device)
            for f in dataclasses.fields(value)
            if f.init
        }
        out = dataclasses.replace(value, **moved)
        for k, v in vars(value).items():  # attributes set after construction
            if k not in moved:
                setattr(out, k, move(v, device))
        return out
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # a NamedTuple
        return type(value)(*(move(v, device) for v in value))
    if isinstance(value, (list, tuple)):
        return type(value)(move(v, device) for v in value)
    if isinstance(value, dict):
        out = {k: move(v, device) for k, v in value.items()}
        if isinstance(value, collections.OrderedDict):  # a module's state_dict
            out = collections.OrderedDict(out)
        if hasattr(value, "_metadata"):  # with the versions its modules' loaders read
            out._metadata = value._metadata
        return out
    return value


def call_on_device(model: torch.nn.Module, fn: Any, *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` with its tensors moved to ``model``'s device, and its
    result moved back to the CPU: the boundary between a model on a GPU and the numpy
    and hull code around it."""
    dev = model_device(model)
    if dev.type == "cpu":
        return fn(*args, **kwargs)
    return move(fn(*move(args, dev), **move(kwargs, dev)), "cpu")


@contextlib.contextmanager
def on_cpu(*modules: torch.nn.Module) -> Iterator[None]:
    """Run a block with ``modules`` on the CPU and put each back on its device after:
    for evaluation and image grids, whose numpy-heavy code runs on the CPU, of a model
    trained on a GPU. Parameters move in place, so optimisers keep their references."""
    devices = [model_device(m) for m in modules]
    if all(d.type == "cpu" for d in devices):
        yield
        return
    for m in modules:
        m.cpu()
    try:
        yield
    finally:
        for m, d in zip(modules, devices, strict=True):
            m.to(d)
