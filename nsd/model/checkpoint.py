"""Load a trained NSD decomposition from its checkpoint (``weights_only=True``).

A checkpoint written by ``nsd-train`` holds the weights, the full config and
the cameras and frame size the model was trained with; :func:`load_decomposition`
rebuilds the model from them and checks a scene's cameras against them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from nsd.core.errors import CheckpointError
from nsd.core.trainer import load_checkpoint
from nsd.model.bi_nvs import BiNVS
from nsd.model.build import build_model

__all__ = ["TrainedDecomposition", "load_decomposition"]


@dataclass
class TrainedDecomposition:
    """A model ready for inference with what it was trained on.

    Attributes:
        model: the BiNVS model (eval mode).
        config: the training config.
        cameras: camera names seen in training.
        frame_hw: training frame size (H, W).
        path: the checkpoint file.
        step: training steps done.
    """

    model: BiNVS
    config: DictConfig
    cameras: list[str]
    frame_hw: tuple[int, int]
    path: Path
    step: int

    def check_cameras(self, names: Sequence[str], scene: str | os.PathLike) -> None:
        """Raise :class:`CheckpointError` if the scene has cameras the model never saw."""
        unknown = [n for n in names if n not in self.cameras]
        if unknown:
            raise CheckpointError(
                f"scene {scene} has cameras {unknown} that checkpoint {self.path} was not "
                f"trained with (it knows {self.cameras}); select known cameras or retrain"
            )


def load_decomposition(
    path: str | os.PathLike, device: torch.device | str = "cpu"
) -> TrainedDecomposition:
    """Rebuild the trained BiNVS of an ``nsd-train`` checkpoint (a file or its run folder)
    on ``device`` (:mod:`nsd.core.device`; the checkpoint itself holds CPU tensors)."""

    path = Path(path)
    if path.is_dir():
        path = path / "checkpoint.pt"
    state = load_checkpoint(path)
    cfg: dict[str, Any] = state.get("config") or {}
    if "model" not in cfg or "model" not in state.get("modules", {}):
        raise CheckpointError(f"{path} is not an nsd-train checkpoint (no model or config)")
    config = OmegaConf.create(cfg)
    model = build_model(OmegaConf.to_container(config.model, resolve=True))
    try:
        model.load_state_dict(state["modules"]["model"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not match its config: {e}") from e
    model.to(device).eval()
    task = state.get("task", {})
    if task.get("stage2_started") is False:
        model.cfg.depth = False
    size = task.get("image_size") or list(config.data.image_size)[::-1]
    return TrainedDecomposition(model, config, list(task.get("cameras", [])), tuple(size), path,
                                int(state.get("step", 0)))
