"""``nsd-train``: self-supervised NSD training (Hydra app); the task is :mod:`nsd.training.task`.

``run`` builds the scene data and the task and hands them to the trainer
(:class:`nsd.core.trainer.Trainer`); ``stage=pose`` trains the pose regressor instead
(:mod:`nsd.training.pose_task`).
"""

from __future__ import annotations

import contextlib
import logging
import math

import hydra
from omegaconf import DictConfig

from nsd.core import distributed
from nsd.core.app import check_command_line, reported
from nsd.core.run_folder import RunFolder
from nsd.io.scene_check import check_scene
from nsd.io.scenes import resolve_scene
from nsd.training.train import train

__all__ = ["main"]

log = logging.getLogger(__name__)
PROG = "nsd-train"


@hydra.main(config_path="pkg://nsd.conf", config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    """Train; returns the validation objective (``cfg.objective``) for sweepers."""
    with reported(PROG) as report:
        out_dir = distributed.hydra_run_dir()
        folder = RunFolder(out_dir, PROG, key="hydra.run.dir") if distributed.rank() == 0 \
            else contextlib.nullcontext()
        with folder:
            if distributed.rank() == 0:
                report.attach(folder)
                cameras = list(cfg.data.cameras) if cfg.data.cameras else None
                # before any long work
                check_scene(resolve_scene(cfg.data.scene), cameras, units=cfg.data.units,
                            background=cfg.data.background, workers=int(cfg.threads))
            metrics = train(cfg, out_dir)
            value = metrics.get(cfg.objective, float("nan"))
            log.info("final metrics: %s", metrics)
            return float(value) if value is not None and math.isfinite(value) else float("nan")


def main() -> None:
    """``nsd-train``; also ``torchrun --nproc_per_node=P -m nsd.cli.train`` (docs/scaling.md)."""
    check_command_line(PROG, "train")
    distributed.run_hydra_app(_hydra_main)


if __name__ == "__main__":
    main()
