"""``nsd-run``: one command from a scene folder to per-subject results, stage by stage.

Stages (each writes ``<out>/<stage>/``; see :mod:`nsd.core.stages`: a finished stage
is never recomputed, a changed setting re-runs it and everything downstream)::

    scene     the scene folder (default: the built-in synthetic scene, written once)
    train     NSD / Bi-NVS decomposition (nsd.cli.train.run; an interrupted training
              resumes from its work folder <out>/.train-work-<hash>/)
    evaluate  metrics against ground truth (nsd.cli.evaluate; only scenes with gt/)
    export    COCO masks and boxes, crops, embeddings, MOT tracks, manifest (nsd.export.subjects)
    keypoints 3D keypoints per subject: NeTePu inverse rendering of the visible masks
              (label-free, netepu.geometry) or NSD's pose regressor trained on a few
              3D labels (netepu.keypoints.source=regressor, netepu.pipeline.pose_keypoints)
    texture   texture codes, their re-id embeddings and NNOPCS maps (netepu.embed;
              netepu.texture)
    identities  an identity for every exported row across cameras and time
              (netepu.identities)
    grids     image grids a person can look at: per frame, every camera's input,
              boxes, visible masks and depth order (coloured by subject id)

Usage::

    nsd-run                                   # default scene -> runs/nsd-run/default/
    nsd-run scene=my_scene out=runs/my_scene  # any scene folder
    nsd-run train.trainer.max_minutes=3       # shorter training (train.* is nsd-train's config)
    nsd-run checkpoint=runs/nsd/<run>/checkpoint.pt  # load a trained decomposition instead
    nsd-run +export.crop.size=96 grids.frames=8  # export.* overrides conf/export.yaml

``<out>/pipeline.json`` records every stage's status, wall time and summary.
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import hydra
import numpy as np
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf
from pycocotools import mask as mask_utils

from netepu.pipeline.embed import embed_into_copy
from netepu.pipeline.pose_keypoints import regress_export
from netepu.pipeline.subject_keypoints import invert_export, keypoint_error
from netepu.reid.identities import IDENTITY_METHODS, assign_identities, identity_accuracy
from nsd.cameras.calibration_io import read_calibration
from nsd.cli.evaluate import evaluate_checkpoint, markdown_table
from nsd.cli.train import run as train
from nsd.core.atomic import atomic_write_text
from nsd.core.errors import CheckpointError, ConfigError, NSDError
from nsd.core.stages import Stage, StageResult, StageRunner, config_hash
from nsd.core.trainer import load_checkpoint
from nsd.evaluation.visualise import decomposition_panels, grid
from nsd.export.config import load_export_config
from nsd.export.subjects import export_subjects
from nsd.inference.multiview import InferenceSettings
from nsd.io.embeddings import read_embeddings
from nsd.io.footage import MultiViewFootage
from nsd.io.ground_truth import GroundTruth
from nsd.io.scenes import resolve_scene

__all__ = ["build_stages", "load_run_config", "main", "run_pipeline"]

log = logging.getLogger(__name__)

DEFAULT_SCENE = "default"


def load_run_config(*overrides: str) -> DictConfig:
    """The shipped ``conf/run.yaml`` composed with command-line style overrides.

    Example:
        >>> cfg = load_run_config("grids.frames=2")
        >>> cfg.grids.frames, cfg.train.trainer.max_steps
        (2, 0)
    """

    if GlobalHydra.instance().is_initialized():
        return compose("run", overrides=list(overrides))
    with initialize_config_module("nsd.conf", version_base="1.3"):
        return compose("run", overrides=list(overrides))


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _out_folder(cfg: DictConfig) -> Path:
    if cfg.out:
        return Path(cfg.out).expanduser()
    name = Path(cfg.scene).expanduser().resolve().name if cfg.scene else DEFAULT_SCENE
    return Path("runs") / "nsd-run" / name


# ------------------------------------------------------------------ stages
def _scene_stage(cfg: DictConfig) -> Stage:
    spec = str(Path(cfg.scene).expanduser().resolve()) if cfg.scene else DEFAULT_SCENE

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        path = resolve_scene(None if spec == DEFAULT_SCENE else spec)
        if not path.is_dir():
            raise ConfigError(f"scene: {path} is not a folder (give scene=<scene folder>)")
        rig = read_calibration(path)
        footage = MultiViewFootage(path)
        summary = {
            "path": str(path.resolve()),
            "cameras": list(rig.names),
            "frames": int(footage.num_frames),
            "ground_truth": GroundTruth.exists(path),
        }
        atomic_write_text(out / "scene.json", json.dumps(summary, indent=2))
        return summary

    return Stage("scene", run, {"scene": spec})


def _train_config(cfg: DictConfig) -> DictConfig:
    """The ``train`` section as an ``nsd-train`` config (its run-folder settings,
    ``train.hydra``, do not apply here)."""
    return OmegaConf.create({k: _container(v) for k, v in cfg.train.items() if k != "hydra"})


def _load_stage(path: Path) -> Stage:
    """The ``train`` stage when ``checkpoint=`` names a trained decomposition: copied, not
    trained (the stage re-runs when the file changes)."""

    if not path.is_file():
        raise ConfigError(f"checkpoint: {path} does not exist (an nsd-train checkpoint.pt)")
    st = path.stat()
    settings = {"checkpoint": str(path.resolve()), "size": st.st_size, "mtime": st.st_mtime_ns}

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        state = load_checkpoint(path)
        config = state.get("config") or {}
        if "model" not in state.get("modules", {}) or config.get("stage") != "decomposition":
            raise CheckpointError(
                f"checkpoint: {path} is not an NSD decomposition checkpoint (nsd-train "
                "stage=decomposition)"
            )
        shutil.copyfile(path, out / "checkpoint.pt")
        return {"checkpoint": "checkpoint.pt", "steps": int(state.get("step", 0)),
                "loaded_from": str(path)}  # fmt: skip

    return Stage("train", run, settings, needs=("scene",))


def _train_stage(cfg: DictConfig, ground_truth: bool) -> Stage:
    _check_keypoint_source(cfg, ground_truth)  # before any training
    if cfg.get("checkpoint"):
        return _load_stage(Path(str(cfg.checkpoint)))
    tcfg = _train_config(cfg)

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        c = tcfg.copy()
        c.data.scene = up["scene"].summary["path"]
        # trained in a work folder that survives an interruption (exact resume), moved at the end
        work = out.parent / f".train-work-{config_hash(_container(c))}"
        metrics = train(c, work)
        for item in work.iterdir():
            shutil.move(str(item), out / item.name)
        work.rmdir()

        return {
            "checkpoint": "checkpoint.pt",
            "steps": int(load_checkpoint(out / "checkpoint.pt").get("step", 0)),
            "metrics": {k: float(v) for k, v in metrics.items() if isinstance(v, int | float)},
        }

    return Stage("train", run, _container(tcfg), needs=("scene",))


def _checkpoint(up: dict[str, StageResult]) -> Path:
    train = up["train"]
    return train.folder / train.summary["checkpoint"]


def _inference(cfg: DictConfig) -> dict[str, Any]:
    """The run's inference settings (``train.inference``), used by evaluate and export."""
    return _container(cfg.train.inference)


def _evaluate_stage(cfg: DictConfig, ground_truth: bool) -> Stage:
    e = cfg.evaluate
    inference = _inference(cfg)

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        frames = e.frames if isinstance(e.frames, str) else list(e.frames)
        metrics = evaluate_checkpoint(
            _checkpoint(up),
            up["scene"].summary["path"],
            frames,
            int(e.max_frames),
            str(e.refine),
            InferenceSettings.from_config(inference),
        )
        metrics = {k: float(v) for k, v in metrics.items()}
        atomic_write_text(out / "eval.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "eval.md", markdown_table(metrics))
        return {"metrics": metrics}

    why = (
        ""
        if e.enabled and ground_truth
        else ("evaluate.enabled=false" if not e.enabled else "the scene has no ground truth (gt/)")
    )
    return Stage(
        "evaluate",
        run,
        {**_container(e), "inference": inference},
        needs=("scene", "train"),
        enabled=not why,
        why_disabled=why,
    )


def _export_stage(cfg: DictConfig) -> Stage:
    overrides = _container(OmegaConf.merge({"inference": _inference(cfg)}, cfg.export))

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        ecfg = OmegaConf.merge(load_export_config(), overrides)
        ecfg.checkpoint = str(_checkpoint(up))
        ecfg.scene = up["scene"].summary["path"]
        ecfg.out = str(out)  # the export is built atomically and replaces the stage's folder
        ecfg.overwrite = True
        s = export_subjects(ecfg)
        return {
            "frames": s.frames,
            "camera_frames": s.camera_frames,
            "subjects": s.subjects,
            "tracks": s.tracks,
            "seconds": round(s.seconds, 3),
        }

    return Stage("export", run, overrides, needs=("scene", "train"))


KEYPOINT_SOURCES = ("inverse", "regressor")
_INVERSE_KEYS = ("frame_step", "min_views", "min_area", "steps", "templates", "max_subject_frames")


def _check_keypoint_source(cfg: DictConfig, ground_truth: bool) -> None:
    """Fail before training on a keypoint source the scene cannot serve."""
    source = cfg.netepu.keypoints.source
    if source not in KEYPOINT_SOURCES:
        raise ConfigError(
            f"netepu.keypoints.source must be one of {KEYPOINT_SOURCES}, got {source!r}"
        )
    if source == "regressor" and not ground_truth:
        raise ConfigError(
            "netepu.keypoints.source=regressor trains NSD's pose regressor from a few 3D "
            "keypoint labels, and this scene has none (no gt/ folder); use source=inverse "
            "(label-free, needs netepu.geometry)"
        )


def _keypoints_stage(cfg: DictConfig) -> Stage:
    n = cfg.netepu
    k = n.keypoints
    regress = k.source == "regressor"
    settings = {"source": k.source, **{name: k[name] for name in _INVERSE_KEYS}}
    if regress:  # the regressor is trained on the decomposition of the train stage
        settings |= {"label_fraction": k.label_fraction, "regressor_steps": k.regressor_steps}
    else:
        settings["geometry"] = n.geometry

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        scene = up["scene"].summary["path"]
        export = up["export"].folder
        if regress:
            summary = _regress_keypoints(cfg, scene, _checkpoint(up), export, out)
        else:
            summary = invert_export(
                export, scene, n.geometry, out, **{name: k[name] for name in _INVERSE_KEYS}
            )
        if up["scene"].summary["ground_truth"]:
            summary["accuracy"] = keypoint_error(export, scene, out / "keypoints3d.npz")
        return summary

    return Stage(
        "keypoints",
        run,
        settings,
        needs=("scene", "train", "export") if regress else ("scene", "export"),
        enabled=regress or n.geometry is not None,
        why_disabled="no geometry model (netepu.geometry=null) and source=inverse",
    )


def _regress_keypoints(
    cfg: DictConfig, scene: str, checkpoint: Path, export: Path, out: Path
) -> dict[str, Any]:
    """Train NSD's pose regressor (stage 3) on the frozen decomposition with
    ``label_fraction`` of the training frames labelled, then regress the exported subjects."""

    k = cfg.netepu.keypoints
    c = OmegaConf.create(load_checkpoint(checkpoint)["config"])  # as trained (or loaded)
    c.data.scene = scene
    c.trainer.progress = bool(cfg.train.trainer.progress)
    c.stage, c.init_from = "pose", str(checkpoint)
    c.pose.label_fraction = float(k.label_fraction)
    c.trainer.max_steps, c.trainer.max_minutes = int(k.regressor_steps), 0.0
    c.trainer.eval_at_minutes = []
    metrics = train(c, out / "pose")
    summary = regress_export(
        export, scene, out / "pose" / "checkpoint.pt", out, int(k.frame_step), max(2, k.min_views)
    )
    summary["regressor"] = {
        "held_out_mpjpe_mm": float(metrics.get("mpjpe_mm", float("nan"))),
        "labelled_frames": float(metrics.get("labelled_frames", float("nan"))),
    }
    return summary


def _texture_stage(cfg: DictConfig, have_keypoints: bool) -> Stage:
    n = cfg.netepu

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        kp = up["keypoints"].folder / "keypoints3d.npz" if have_keypoints else None
        res = embed_into_copy(
            up["export"].folder, out, n.texture, kp, up["scene"].summary["path"],
            maps=out / "nnopcs.npz",
        )  # fmt: skip
        return {
            "table": Path(res["path"]).name,
            "rows": res["rows"],
            "encoded": res["encoded"],
            "maps": "nnopcs.npz",
        }

    return Stage(
        "texture",
        run,
        {"texture": n.texture},
        needs=("scene", "export", "keypoints"),
        enabled=n.texture is not None,
        why_disabled="no texture model (netepu.texture=null)",
    )


def _identities_stage(cfg: DictConfig, have_texture: bool, ground_truth: bool) -> Stage:
    i = cfg.netepu.identities
    column = str(i.column) if have_texture else "app"

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        if not have_texture:
            log.info("identities: no texture codes (texture stage skipped): NSD appearance vectors")
        source = up["texture"].folder if have_texture else up["export"].folder
        keys = ["id", "camera", "frame", "subject_id"]
        table = read_embeddings(source, [*keys, column])  # rows without a code hold NaN
        identity, summary = assign_identities(
            table, column, int(i.k), str(i.method), int(i.restarts)
        )
        lines = [",".join([*keys, "identity"])] + [
            ",".join(map(str, row))
            for row in zip(*(table[c].tolist() for c in keys), identity.tolist(), strict=True)
        ]
        atomic_write_text(out / "identities.csv", "\n".join(lines) + "\n")
        summary["column"] = column
        if ground_truth:
            summary["accuracy"] = identity_accuracy(
                up["export"].folder,
                up["scene"].summary["path"],
                table["id"],
                identity,
            )
        return summary

    return Stage(
        "identities",
        run,
        {**_container(i), "column": column},
        needs=("scene", "export", "texture"),
        enabled=bool(i.enabled),
        why_disabled="netepu.identities.enabled=false",
    )


def _grids_stage(cfg: DictConfig) -> Stage:
    g = cfg.grids

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        files = write_grids(
            up["export"].folder, up["scene"].summary["path"], out, int(g.frames), int(g.size)
        )
        return {"files": [f.name for f in files]}

    return Stage(
        "grids",
        run,
        _container(g),
        needs=("scene", "export"),
        enabled=g.frames > 0,
        why_disabled="grids.frames=0",
    )


def write_grids(
    export: str | Path, scene: str | Path, out: str | Path, frames: int, size: int
) -> list[Path]:
    """One PNG per frame (``frames`` spread over the export): a row per camera with the input,
    boxes, visible masks and depth order (nearest brightest), coloured by subject id.

    Args:
        export: an ``nsd-export`` folder.
        scene: its scene folder (for the input frames).
        out: folder for ``frame_<t>.png``.
        frames: how many frames.
        size: each panel's longer side in pixels.
    """

    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    by_image: dict[int, list[dict]] = {}
    for a in coco["annotations"]:
        by_image.setdefault(int(a["image_id"]), []).append(a)
    images = {(im["camera"], int(im["frame"])): im for im in coco["images"]}
    all_frames = sorted({t for _, t in images})
    if not all_frames:
        return []
    pick = np.asarray(all_frames)[
        np.unique(np.linspace(0, len(all_frames) - 1, min(frames, len(all_frames))).round()).astype(
            int
        )
    ]
    footage = MultiViewFootage(scene)
    out = Path(out)
    written = []
    for t in pick.tolist():
        rows = []
        for v, cam in enumerate(footage.camera_names):
            if (cam, t) not in images:
                continue
            img = footage.sources[v].read(t)
            im = images[(cam, t)]
            anns = by_image.get(int(im["id"]), [])
            h, w = img.shape[:2]
            s = size / max(h, w)  # drawn at panel size, so that boxes and labels stay visible
            pw, ph = round(w * s), round(h * s)
            img = cv2.resize(img, (pw, ph), interpolation=cv2.INTER_AREA)
            masks = np.zeros((len(anns), ph, pw), np.float32)
            for k, a in enumerate(anns):
                m = mask_utils.decode(a["segmentation"]).astype(np.float32)
                masks[k] = cv2.resize(m, (pw, ph), interpolation=cv2.INTER_AREA)
            for a in anns:
                a["bbox"] = [c * s for c in a["bbox"]]
            dec = _OneFrame(anns, masks)
            panels = [img, *decomposition_panels(img, dec, 0, [a["subject_id"] for a in anns])]
            rows.append(panels)
        if rows:
            path = out / f"frame_{t:06d}.png"
            cv2.imwrite(str(path), cv2.cvtColor(grid(rows), cv2.COLOR_RGB2BGR))
            written.append(path)
    return written


class _OneFrame:
    """The fields of :class:`nsd.inference.single.Decomposition` that the panels read, from COCO."""

    def __init__(self, anns: list[dict], masks: np.ndarray) -> None:
        n = len(anns)
        self.active = torch.ones(1, n, dtype=torch.bool)
        self.masks = torch.from_numpy(masks)[None]
        self.boxes = torch.tensor([a["bbox"] for a in anns], dtype=torch.float32).reshape(1, n, 4)
        self.depths = torch.tensor([a["depth"] for a in anns], dtype=torch.float32).reshape(1, n)


# ------------------------------------------------------------------ pipeline
def _ran(runner: StageRunner, name: str) -> bool:
    """The stage produced outputs (now or earlier), i.e. it was not disabled."""
    return "disabled" not in runner.results[name].summary


def build_stages(cfg: DictConfig, runner: StageRunner) -> list[Callable[[], Stage]]:
    """Stage factories in order (a factory may read the results of earlier stages)."""
    return [
        lambda: _scene_stage(cfg),
        lambda: _train_stage(cfg, bool(runner.results["scene"].summary["ground_truth"])),
        lambda: _evaluate_stage(cfg, bool(runner.results["scene"].summary["ground_truth"])),
        lambda: _export_stage(cfg),
        lambda: _keypoints_stage(cfg),
        lambda: _texture_stage(cfg, _ran(runner, "keypoints")),
        lambda: _identities_stage(
            cfg, _ran(runner, "texture"), bool(runner.results["scene"].summary["ground_truth"])
        ),
        lambda: _grids_stage(cfg),
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
            else f"ran in {r.seconds:.1f} s"
        )
        lines.append(f"  {name:<10} {status}")
    return "\n".join(lines)


@hydra.main(config_path="pkg://nsd.conf", config_name="run", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    out = _out_folder(cfg)
    out.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(name)s: %(message)s",
        handlers=[logging.StreamHandler(), logging.FileHandler(out / "run.log")],
        force=True,
    )
    for logger in logging.Logger.manager.loggerDict.values():  # hydra's logging config
        if isinstance(logger, logging.Logger):  # disabled the loggers that existed before it
            logger.disabled = False
    torch.set_num_threads(max(1, min(torch.get_num_threads(), int(cfg.threads))))
    try:
        results = run_pipeline(cfg)
    except (NSDError, FileExistsError) as e:
        print(f"nsd-run: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(_report(out, results))


def main() -> None:
    """Entry point of ``nsd-run``."""
    _hydra_main()


if __name__ == "__main__":
    main()
