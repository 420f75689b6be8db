"""``netepu-train``: the Hydra app that trains NeTePu's stages with the shared trainer.

``stage`` selects what is trained; each stage is a builder in :data:`STAGES`
that turns the config into a :class:`nsd.core.trainer.TrainTask`. The loop,
checkpoints (exact resume), logs, progress bar and time budgets are
:class:`nsd.core.trainer.Trainer`'s, shared with ``nsd-train``. The texture stage
(:mod:`netepu.texture.stage`) trains on a frozen geometry checkpoint given
by ``init_from``.

Examples::

    netepu-train trainer.max_minutes=20 trainer.max_steps=0
    netepu-train netepu/model=reference trainer.max_steps=200
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from netepu.geometry.stage import build_geometry_stage
from netepu.texture.stage import build_texture_stage
from nsd.core.app import check_command_line, reported
from nsd.core.device import resolve_device
from nsd.core.errors import ConfigError
from nsd.core.run_folder import RunFolder
from nsd.core.threads import set_threads
from nsd.core.trainer import Trainer, TrainerConfig, load_checkpoint, seed_everything

__all__ = ["STAGES", "main", "run"]

log = logging.getLogger(__name__)
PROG = "netepu-train"


STAGES: dict[str, Callable[[DictConfig], tuple[Any, dict[str, Any]]]] = {
    "geometry": build_geometry_stage,
    "texture": build_texture_stage,
}


def run(cfg: DictConfig, out_dir: Path) -> dict[str, float]:
    """Train ``cfg.stage`` into ``out_dir``; returns the final evaluation metrics."""
    set_threads(int(cfg.threads))
    device = resolve_device(cfg.device)
    if cfg.stage not in STAGES:
        raise ConfigError(f"stage must be one of {sorted(STAGES)}, got {cfg.stage!r}")
    tcfg = TrainerConfig.from_config(OmegaConf.to_container(cfg.trainer, resolve=True))
    seed_everything(tcfg.seed)  # model initialisation is part of the seeded run
    task, found = STAGES[cfg.stage](cfg)
    if cfg.get("init_from"):
        state = load_checkpoint(cfg.init_from)
        for name, module in task.modules().items():
            if name in state["modules"]:
                module.load_state_dict(state["modules"][name])
    config = OmegaConf.to_container(cfg, resolve=True)
    found = dict(found)
    if "model" in found:  # a stage built on a checkpoint (texture) records its geometry model
        config["netepu"]["model"] = found.pop("model")
    config["netepu"]["data"].update(found)
    task.to(device)  # after the weights of init_from; optimisers keep their parameters
    log.info("models run on %s", device)
    trainer = Trainer(task, tcfg, out_dir, config)
    metrics = trainer.fit()
    metrics["iterations_per_second"] = trainer.throughput()
    return metrics


@hydra.main(config_path="pkg://nsd.conf", config_name="netepu_train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    """Train; returns the validation objective (``cfg.objective``) for sweepers."""
    with reported(PROG) as report:
        out_dir = Path(HydraConfig.get().runtime.output_dir)
        with RunFolder(out_dir, PROG, key="hydra.run.dir") as folder:
            report.attach(folder)
            metrics = run(cfg, out_dir)
            log.info("final metrics: %s", metrics)
            value = metrics.get(cfg.objective, float("nan"))
            return float(value) if value is not None and math.isfinite(value) else float("nan")


def main() -> None:
    """Entry point of ``netepu-train``: the command line is checked before any work."""
    check_command_line(PROG, "netepu_train")
    _hydra_main()


if __name__ == "__main__":
    main()
