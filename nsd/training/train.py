"""The NSD training driver: scene data, the task (decomposition or pose), the trainer."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from nsd.cameras.calibration_io import read_calibration
from nsd.cameras.units import file_units
from nsd.core.device import resolve_device
from nsd.core.errors import ConfigError
from nsd.core.threads import set_threads
from nsd.core.trainer import Trainer, TrainerConfig, load_checkpoint, seed_everything
from nsd.io.ground_truth import GroundTruth
from nsd.io.labels import read_pose_labels
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.training.pose_task import PoseTask
from nsd.training.task import NSDTask

__all__ = ["train"]

log = logging.getLogger(__name__)


def train(cfg: DictConfig, out_dir: Path) -> dict[str, float]:
    """Train according to ``cfg`` into ``out_dir``; returns the final metrics."""
    log.info("torch uses %d CPU threads", set_threads(int(cfg.threads)))
    device = resolve_device(cfg.device)
    log.info("models run on %s", device)
    scene = resolve_scene(cfg.data.scene)
    data = SceneData(
        scene, cfg.data.image_size, cfg.data.cameras, cfg.data.val_fraction, cfg.data.max_frames,
        cfg.data.units, cfg.data.frame_stride, cfg.data.background, int(cfg.threads),
    )

    gt = GroundTruth.load(scene) if GroundTruth.exists(scene) else None
    if cfg.stage == "pose" and cfg.pose.get("labels"):  # a user's labels, in the rig's unit
        unit = file_units(read_calibration(scene, "m"), cfg.data.units)
        gt = read_pose_labels(cfg.pose.labels, data.footage.native_rig, unit)
    tcfg = TrainerConfig.from_config(OmegaConf.to_container(cfg.trainer, resolve=True))
    seed_everything(tcfg.seed)  # model initialisation is part of the seeded train
    if cfg.stage == "pose":
        task = PoseTask(cfg, data, gt, device)
    elif cfg.stage == "decomposition":
        task = NSDTask(cfg, data, gt, device)
    else:
        raise ConfigError(f"stage must be 'decomposition' or 'pose', got {cfg.stage!r}")
    if cfg.init_from:
        state = load_checkpoint(cfg.init_from)
        task.model.load_state_dict(state["modules"]["model"])
    trainer = Trainer(task, tcfg, out_dir, OmegaConf.to_container(cfg, resolve=True))
    metrics = trainer.fit()
    metrics["iterations_per_second"] = trainer.throughput()
    return metrics
