"""The NSD training driver: scene data, the task (decomposition or pose), the trainer."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from nsd.cameras.calibration_io import read_calibration
from nsd.cameras.units import file_units
from nsd.core.device import resolve_device
from nsd.core.errors import ConfigError
from nsd.core.threads import set_threads
from nsd.core.trainer import Trainer, TrainerConfig, load_checkpoint, seed_everything
from nsd.cues.count import countable
from nsd.io.ground_truth import GroundTruth
from nsd.io.labels import read_pose_labels
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.training.pose_task import PoseTask
from nsd.training.task import NSDTask

__all__ = ["hull_count_warning", "train", "window_count_warning"]

log = logging.getLogger(__name__)


def window_count_warning(num_windows: int, presence: bool, individuals: int) -> str | None:
    """What is wrong with ``model.num_windows`` for a scene that declares how many
    individuals it holds (``gt/scene.json`` of an ``nsd-synth`` scene), or None.

    A fixed count (``presence`` off) must be the number of individuals: fewer windows each
    hold several bodies, more cut bodies in pieces, in every camera alike, which no
    label-free figure of the run can see. An upper bound (presence on) must not be below it.

        >>> window_count_warning(2, False, 2) is None, window_count_warning(6, True, 5) is None
        (True, True)
        >>> window_count_warning(2, False, 5)[:62]
        'model.num_windows=2 but the scene declares 5 individuals (gt/s'
    """
    if num_windows == individuals or (presence and num_windows > individuals):
        return None
    what = ("each window will hold several bodies" if num_windows < individuals else
            "the visual hull's clusters will cut bodies in pieces")
    return (f"model.num_windows={num_windows} but the scene declares {individuals} "
            f"individual{'s' * (individuals != 1)} (gt/scene.json): {what}; set "
            f"model.num_windows={individuals} (nsd-run: train.model.num_windows)")


def hull_count_warning(num_windows: int, bodies: int, counts: np.ndarray) -> str | None:
    """What is wrong with ``model.num_windows`` for footage whose visual hull shows
    ``bodies`` separate bodies (:func:`nsd.cues.count.scene_bodies`, a lower bound on the
    individuals; ``counts`` per frame looked at), or None: more bodies than windows warn,
    fixed count or upper bound.

        >>> hull_count_warning(2, 2, np.array([1, 2, 2])) is None
        True
        >>> hull_count_warning(2, 4, np.array([2, 4, 4, 5]))[:63]
        'the visual hull shows 4 separate bodies in more than a tenth of'
    """
    if bodies <= num_windows:
        return None
    share = float(np.mean(counts > num_windows))
    return (f"the visual hull shows {bodies} separate bodies in more than a tenth of the "
            f"{len(counts)} frames looked at (more than {num_windows} in {share:.0%} of them), "
            f"more than model.num_windows={num_windows}: each window will hold several "
            f"bodies; set model.num_windows to the number of individuals, at least {bodies} "
            "(nsd-run: train.model.num_windows)")


def _check_window_count(cfg: DictConfig, data: SceneData, gt: GroundTruth | None,
                        scene: Path) -> None:
    """Warn before training when ``model.num_windows`` cannot fit the scene: against the
    individuals a synthetic scene declares, else against the bodies its visual hull shows
    (footage :func:`nsd.cues.count.countable`)."""
    k, presence = int(cfg.model.num_windows), bool(cfg.model.detector.presence)
    if gt is not None:
        problem = window_count_warning(k, presence, len(gt.scene.individuals))
    elif not countable(data.frames.shape[0], data.num_views):
        return  # too short, or too few cameras, for the hull to count
    else:
        problem = hull_count_warning(k, *data.hull_bodies(
            cfg.loss.evidence_threshold, cfg.loss.evidence_softness,
            cfg.prior_proposal.resolution, cfg.prior_proposal.min_views))
    if problem:
        log.warning("scene %s: %s", scene.name, problem)


def train(cfg: DictConfig, out_dir: Path) -> dict[str, float]:
    """Train according to ``cfg`` into ``out_dir``; returns the final metrics."""
    log.info("torch uses %d CPU threads", set_threads(int(cfg.threads)))
    device = resolve_device(cfg.device)
    log.info("models run on %s", device)
    scene = resolve_scene(cfg.data.scene)
    data = SceneData(
        scene, cfg.data.image_size, cfg.data.cameras, cfg.data.val_fraction, cfg.data.max_frames,
        cfg.data.units, cfg.data.frame_stride, cfg.data.background,
    )

    gt = GroundTruth.load(scene) if GroundTruth.exists(scene) else None
    if cfg.stage == "decomposition":
        _check_window_count(cfg, data, gt, Path(scene))
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
