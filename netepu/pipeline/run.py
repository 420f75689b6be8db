"""``nsd-run``: one command from a scene folder to per-subject results, stage by stage.

Stages (each writes ``<out>/<stage>/``; see :mod:`nsd.core.stages`: a finished stage
is never recomputed, a changed setting re-runs it and everything downstream)::

    scene     the scene folder (default: the built-in synthetic scene, written once)
    train     NSD / Bi-NVS decomposition (nsd.training.train.train; an interrupted training
              resumes from its work folder <out>/.train-work-<hash>/)
    evaluate  metrics against ground truth (nsd.cli.evaluate; only scenes with gt/)
    export    COCO masks and boxes, crops, embeddings, MOT tracks, manifest (nsd.export.subjects)
    keypoints 3D keypoints per subject: NeTePu inverse rendering of the visible masks
              (label-free, netepu.geometry) or NSD's pose regressor trained on a few
              3D labels (netepu.keypoints.source=regressor, netepu.pipeline.pose_keypoints)
    texture   texture codes, their re-id embeddings and NNOPCS maps (netepu.embed;
              netepu.texture)
    identities  an identity for every exported row across cameras and time
              (netepu.identities); MOT metrics and identity tracks (identities/tracks/)
    quality   a label-free quality report: foreground explained, masks confirmed by the
              other cameras, identity stability, grids of the worst frames (nsd.evaluation.quality)
    formats   the export in the pose tools' files (SLEAP, NWB, DeepLabCut, TRC, C3D)
    overlays  a video per camera: masks, boxes, identities, depth order (nsd.export.overlay)
    grids     image grids a person can look at: per frame, every camera's input,
              boxes, visible masks and depth order (coloured by subject id)

Usage::

    nsd-run                                   # default scene -> runs/nsd-run/default/
    nsd-run scene=my_scene out=runs/my_scene  # any scene folder
    nsd-run train.trainer.max_minutes=3       # shorter training (train.* is nsd-train's config)
    nsd-run checkpoint=runs/nsd/<run>/checkpoint.pt  # load a trained decomposition instead
    nsd-run +export.crop.size=96 grids.frames=8  # export.* overrides conf/export.yaml

``<out>/pipeline.json`` records every stage's status, wall time, peak memory and summary.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

import hydra
from omegaconf import DictConfig

from netepu.pipeline.species_models import SpeciesModels, resolve_scene_models
from netepu.pipeline.stages import (
    DEFAULT_SCENE,
    evaluate_stage,
    export_stage,
    formats_stage,
    grids_stage,
    identities_stage,
    keypoints_stage,
    overlays_stage,
    quality_stage,
    scene_stage,
    texture_stage,
    train_stage,
)
from netepu.reid.identities import IDENTITY_METHODS
from nsd.core.app import check_command_line, reported
from nsd.core.atomic import atomic_write_text
from nsd.core.config import compose_app
from nsd.core.device import resolve_device
from nsd.core.errors import ConfigError
from nsd.core.run_folder import RunFolder
from nsd.core.stages import Stage, StageResult, StageRunner
from nsd.core.threads import set_threads

__all__ = ["build_stages", "load_run_config", "main", "run_pipeline"]

log = logging.getLogger(__name__)
PROG = "nsd-run"



def load_run_config(*overrides: str) -> DictConfig:
    """The shipped ``conf/run.yaml`` composed with command-line style overrides.

    Example:
        >>> cfg = load_run_config("grids.frames=2")
        >>> cfg.grids.frames, cfg.train.trainer.max_steps
        (2, 0)
    """
    return compose_app("run", overrides)


def _out_folder(cfg: DictConfig) -> Path:
    if cfg.out:
        return Path(cfg.out).expanduser()
    name = Path(cfg.scene).expanduser().resolve().name if cfg.scene else DEFAULT_SCENE
    return Path("runs") / "nsd-run" / name


# ------------------------------------------------------------------ pipeline
def _ran(runner: StageRunner, name: str) -> bool:
    """The stage produced outputs (now or earlier), i.e. it was not disabled."""
    return "disabled" not in runner.results[name].summary


def build_stages(cfg: DictConfig, runner: StageRunner) -> list[Callable[[], Stage]]:
    """Stage factories in order (a factory may read the results of earlier stages)."""

    resolved: list[SpeciesModels] = []

    def models() -> list[SpeciesModels]:  # the NeTePu models of the scene's species (after
        if not resolved:  # scene), once for the keypoints, texture and identities stages
            n = cfg.netepu
            resolved.extend(resolve_scene_models(
                str(n.species), n.geometry, n.texture, runner.results["scene"].summary["path"],
                initialiser=n.keypoints.initialiser))
        return resolved

    def several() -> list[str]:  # the species of a run of several, each with its own models
        inverse = cfg.netepu.keypoints.source != "regressor"  # the regressor fits one body
        return [m.species for m in models()] if len(models()) > 1 and inverse else []

    def chosen() -> list[SpeciesModels]:  # one set per species of a run of several, else one
        return models() if several() else models()[:1]

    return [
        lambda: scene_stage(cfg),
        lambda: train_stage(cfg, bool(runner.results["scene"].summary["ground_truth"])),
        lambda: evaluate_stage(cfg, bool(runner.results["scene"].summary["ground_truth"])),
        lambda: export_stage(cfg),
        lambda: keypoints_stage(cfg, chosen()),
        lambda: texture_stage(cfg, chosen(), _ran(runner, "keypoints")),
        lambda: identities_stage(
            cfg, _ran(runner, "texture"), bool(runner.results["scene"].summary["ground_truth"]),
            several(),
        ),
        lambda: quality_stage(cfg, _ran(runner, "identities")),
        lambda: formats_stage(cfg, _ran(runner, "identities"),
                              [m.species for m in chosen()] if _ran(runner, "keypoints")
                              else []),
        lambda: overlays_stage(cfg, _ran(runner, "identities")),
        lambda: grids_stage(cfg),
    ]


def run_pipeline(cfg: DictConfig) -> dict[str, StageResult]:
    """Run (or resume) every stage into ``cfg.out``; returns the stage results by name.

    Raises:
        ConfigError: an unknown ``netepu.identities.method`` (checked before any stage runs).
    """

    if cfg.netepu.identities.method not in IDENTITY_METHODS:
        raise ConfigError(
            f"netepu.identities.method must be one of {IDENTITY_METHODS}, "
            f"got {cfg.netepu.identities.method!r}"
        )
    out = _out_folder(cfg)
    out.mkdir(parents=True, exist_ok=True)
    runner = StageRunner(out)
    for make in build_stages(cfg, runner):
        runner.run(make())
    record = {
        name: {
            "status": "disabled"
            if "disabled" in r.summary
            else ("done earlier" if r.skipped else "ran"),
            "seconds": round(r.seconds, 3),
            "peak_rss_mb": r.peak_rss_mb,
            "summary": r.summary,
        }
        for name, r in runner.results.items()
    }
    atomic_write_text(out / "pipeline.json", json.dumps(record, indent=2, default=str))
    return runner.results


def _report(out: Path, results: dict[str, StageResult]) -> str:
    lines = [f"nsd-run: results in {out}/"]
    for name, r in results.items():
        status = (
            f"skipped ({r.summary['disabled']})"
            if "disabled" in r.summary
            else "done earlier, reused"
            if r.skipped
            else f"ran in {r.seconds:.1f} s, peak memory {r.peak_rss_mb:.0f} MiB"
        )
        lines.append(f"  {name:<10} {status}")
    return "\n".join(lines)


@hydra.main(config_path="pkg://nsd.conf", config_name="run", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    with reported(PROG) as report, RunFolder(_out_folder(cfg), PROG) as folder:
        report.attach(folder)
        logging.basicConfig(  # stderr is the run folder's tee: run.log receives it too
            level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
            handlers=[logging.StreamHandler()], force=True,
        )
        for logger in logging.Logger.manager.loggerDict.values():  # hydra's logging config
            if isinstance(logger, logging.Logger):  # disabled the loggers that existed before it
                logger.disabled = False
        log.info("torch uses %d CPU threads", set_threads(int(cfg.threads)))
        log.info("models run on %s", resolve_device(cfg.device))  # a wrong device fails here
        results = run_pipeline(cfg)
        print(_report(folder.folder, results))


def main() -> None:
    """Entry point of ``nsd-run``: the command line is checked before any work."""
    check_command_line(PROG, "run")
    _hydra_main()


if __name__ == "__main__":
    main()
