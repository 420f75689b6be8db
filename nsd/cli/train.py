"""``nsd-train``: self-supervised NSD training (Hydra app); the task is :mod:`nsd.training.task`.

``run`` builds the scene data and the task and hands them to the trainer
(:class:`nsd.core.trainer.Trainer`); ``stage=pose`` trains the pose regressor instead
(:mod:`nsd.training.pose_task`).
"""

from __future__ import annotations

import logging
import math

import hydra
from omegaconf import DictConfig

from nsd.core import distributed
from nsd.training.train import train

__all__ = ["main"]

log = logging.getLogger(__name__)


@hydra.main(config_path="pkg://nsd.conf", config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    """Train; returns the validation objective (``cfg.objective``) for sweepers."""
    out_dir = distributed.hydra_run_dir()
    metrics = train(cfg, out_dir)
    value = metrics.get(cfg.objective, float("nan"))
    log.info("final metrics: %s", metrics)
    return float(value) if value is not None and math.isfinite(value) else float("nan")


def main() -> None:
    """``nsd-train``; also ``torchrun --nproc_per_node=P -m nsd.cli.train`` (docs/scaling.md)."""
    distributed.run_hydra_app(_hydra_main)


if __name__ == "__main__":
    main()
