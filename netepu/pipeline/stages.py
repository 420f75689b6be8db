"""The stages of ``nsd-run``, one factory each: scene, train, evaluate, export, keypoints,
texture, identities, formats, overlays, grids.

Each factory returns a :class:`nsd.core.stages.Stage` whose ``run(out, upstream)`` writes
its folder; :mod:`netepu.pipeline.run` chains them and decides which ones a run needs.
"""

from __future__ import annotations

import functools
import json
import logging
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from netepu.pipeline.embed import embed_into_copy
from netepu.pipeline.pose_keypoints import regress_export
from netepu.pipeline.species_choice import (
    choose_species,
    read_species_csv,
    species_of_rows,
    split_fits,
    write_species_csv,
)
from netepu.pipeline.species_models import BUILTIN, SpeciesModels
from netepu.pipeline.subject_keypoints import invert_export, load_initialiser_checked
from netepu.reid.identities import (
    SEPARATION_GAP,
    SEPARATION_MIN,
    assign_identities,
    transfer_identities,
)
from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_calibration
from nsd.core.atomic import atomic_write_text
from nsd.core.errors import CheckpointError, ConfigError
from nsd.core.processes import resolve_workers
from nsd.core.stages import Stage, StageResult, config_hash
from nsd.core.trainer import load_checkpoint
from nsd.evaluation.checkpoint import evaluate_checkpoint, markdown_table
from nsd.evaluation.identity import identity_accuracy_by_contact
from nsd.evaluation.pose import keypoint_error, species_accuracy, subject_truth
from nsd.evaluation.quality import quality_markdown, quality_report
from nsd.evaluation.tracking import tracking_metrics
from nsd.export.config import load_export_config
from nsd.export.grids import write_grids
from nsd.export.overlay import write_overlay_videos
from nsd.export.pose_tools import KeypointFile, write_pose_tool_files
from nsd.export.positions import (
    mask_centroids,
    read_positions,
    triangulate_positions,
    write_positions,
)
from nsd.export.subjects import export_subjects
from nsd.inference.multiview import InferenceSettings
from nsd.inference.tracking import position_scale
from nsd.io.background_report import write_background_report
from nsd.io.embeddings import read_embeddings, read_tracklets
from nsd.io.ground_truth import GroundTruth
from nsd.io.identities import identity_by_row, write_identities
from nsd.io.mot import write_identity_tracks
from nsd.io.scene_check import check_scene, scene_fingerprint
from nsd.io.scenes import resolve_scene
from nsd.synth.skeleton import SPECIES as SPECIES_BODIES
from nsd.synth.skeleton import get_species
from nsd.training.train import train

__all__ = [
    "DEFAULT_SCENE",
    "KEYPOINT_SOURCES",
    "evaluate_stage",
    "export_stage",
    "formats_stage",
    "grids_stage",
    "identities_stage",
    "keypoints_stage",
    "look_alike",
    "quality_stage",
    "scene_stage",
    "texture_stage",
    "train_stage",
]

log = logging.getLogger(__name__)

DEFAULT_SCENE = "default"  # the run folder name of the built-in default scene


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


# ------------------------------------------------------------------ stages
def scene_stage(cfg: DictConfig) -> Stage:
    """The scene folder, checked before any long work (:func:`nsd.io.scene_check.check_scene`:
    errors stop the run, warnings are logged and kept in ``scene.json``) and its background
    report (``background/``, :mod:`nsd.io.background_report`); keyed by the folder's content,
    so replacing a video or the calibration re-runs every stage."""
    spec = str(Path(cfg.scene).expanduser().resolve()) if cfg.scene else DEFAULT_SCENE
    path = resolve_scene(None if spec == DEFAULT_SCENE else spec)
    if not path.is_dir():
        raise ConfigError(f"scene: {path} is not a folder (give scene=<scene folder>)")
    cameras = cfg.train.data.cameras
    cameras = list(cameras) if cameras else None

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        check = check_scene(path, cameras, units=cfg.train.data.units,
                            background=cfg.train.data.background, workers=int(cfg.threads))
        write_background_report(check.estimates, check.plates, out / "background",
                                cfg.train.data.background)
        summary = {"path": str(path.resolve()), **check.summary(),
                   "ground_truth": GroundTruth.exists(path)}
        atomic_write_text(out / "scene.json", json.dumps(summary, indent=2))
        return summary

    return Stage("scene", run, {"scene": spec, "cameras": cameras,
                                "content": scene_fingerprint(path),
                                "background": cfg.train.data.background})


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
                "num_windows": config.get("model", {}).get("num_windows"),
                "loaded_from": str(path)}  # fmt: skip

    return Stage("train", run, settings, needs=("scene",))


def train_stage(cfg: DictConfig, ground_truth: bool) -> Stage:
    _check_keypoint_source(cfg, ground_truth)  # before any training
    if cfg.get("checkpoint"):
        return _load_stage(Path(str(cfg.checkpoint)))
    tcfg = _train_config(cfg)

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        c = tcfg.copy()
        c.data.scene = up["scene"].summary["path"]
        c.threads, c.device = cfg.threads, cfg.device  # nsd-run's: one setting for all stages
        # trained in a work folder that survives an interruption (exact resume), moved at the end
        work = out.parent / f".train-work-{config_hash(_container(c))}"
        for stale in out.parent.glob(".train-work-*"):  # of other settings: never resumed
            if stale != work:
                shutil.rmtree(stale, ignore_errors=True)
                log.info("removed %s, the work folder of a training with other settings", stale)
        if (work / "checkpoint.pt").is_file():
            log.info("train: resuming the interrupted training in %s", work)
        metrics = train(c, work)
        for item in work.iterdir():
            shutil.move(str(item), out / item.name)
        work.rmdir()

        state = load_checkpoint(out / "checkpoint.pt")
        return {
            "checkpoint": "checkpoint.pt",
            "steps": int(state.get("step", 0)),
            "num_windows": state["config"]["model"]["num_windows"],  # as settled (auto)
            "metrics": {k: float(v) for k, v in metrics.items() if isinstance(v, int | float)},
        }

    # where and on how many threads it runs is not a result; the inference settings change
    # what evaluate and export make of the checkpoint, not the checkpoint (the training's own
    # progress evaluations keep the settings it ran with)
    settings = {k: v for k, v in _container(tcfg).items()
                if k not in ("threads", "device", "inference")}
    return Stage("train", run, settings, needs=("scene",))


def _train_size(cfg: DictConfig) -> tuple[int, int]:
    """(H, W) of the training frames, at which evaluations compare masks."""
    w, h = cfg.train.data.image_size
    return int(h), int(w)


def _checkpoint(up: dict[str, StageResult]) -> Path:
    train = up["train"]
    return train.folder / train.summary["checkpoint"]


def _inference(cfg: DictConfig) -> dict[str, Any]:
    """The run's inference settings (``train.inference``), used by evaluate and export."""
    return _container(cfg.train.inference)


def evaluate_stage(cfg: DictConfig, ground_truth: bool) -> Stage:
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
            baseline=bool(e.baseline),
            device=cfg.device,
        )
        metrics = {k: float(v) for k, v in metrics.items()}
        atomic_write_text(out / "eval.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "eval.md", markdown_table(metrics))
        return {"metrics": metrics}

    why = (
        ""
        if e.enabled and ground_truth
        else "evaluate.enabled=false" if not e.enabled
        else "the scene has no ground-truth masks (gt/dense/)"
    )
    return Stage(
        "evaluate",
        run,
        {**_container(e), "inference": inference},
        needs=("scene", "train"),
        enabled=not why,
        why_disabled=why,
    )


# export settings that do not change what is exported (or are set per run by the stage)
_EXPORT_NOT_RESULTS = ("checkpoint", "scene", "out", "overwrite", "threads", "device", "workers",
                       "progress")


def export_stage(cfg: DictConfig) -> Stage:
    overrides = _container(OmegaConf.merge({"inference": _inference(cfg)}, cfg.export))
    # keyed by the whole export config, so that a changed shipped default re-runs the export
    composed = _container(OmegaConf.merge(load_export_config(), overrides))
    settings = {k: v for k, v in composed.items() if k not in _EXPORT_NOT_RESULTS}

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        ecfg = OmegaConf.merge(load_export_config(), overrides)
        ecfg.checkpoint = str(_checkpoint(up))
        ecfg.scene = up["scene"].summary["path"]
        ecfg.out = str(out)  # the export is built atomically and replaces the stage's folder
        ecfg.overwrite = True
        for key in ("threads", "device"):  # nsd-run's unless +export.<key> says else
            if key not in cfg.export:
                ecfg[key] = cfg[key]
        s = export_subjects(ecfg)
        return {
            "frames": s.frames,
            "camera_frames": s.camera_frames,
            "subjects": s.subjects,
            "tracks": s.tracks,
            "seconds": round(s.seconds, 3),
        }

    return Stage("export", run, settings, needs=("scene", "train"))


KEYPOINT_SOURCES = ("inverse", "regressor")


_INVERSE_KEYS = ("frame_step", "min_views", "min_area", "steps", "templates", "max_subject_frames",
                 "occlusion", "warm_steps", "smooth_frames", "point_budget", "init_steps",
                 "init_templates", "init_poses", "init_points_per_view", "travel_speed",
                 "heading_tolerance")


def _check_keypoint_source(cfg: DictConfig, ground_truth: bool) -> None:
    """Fail before training on a keypoint source the scene cannot serve, a bad
    ``netepu.keypoints.workers`` or an initialiser file that is not one."""
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
    try:
        resolve_workers(cfg.netepu.keypoints.workers, int(cfg.threads), "cpu")
    except ConfigError as e:
        raise ConfigError(f"netepu.keypoints.{e}") from None
    init = cfg.netepu.keypoints.get("initialiser")
    if source == "inverse" and init is not None and str(init) != BUILTIN:
        load_initialiser_checked(init)  # a missing or foreign file: now, not after training


def keypoints_stage(cfg: DictConfig, models: list[SpeciesModels]) -> Stage:
    """3D keypoints of the exported subjects: NeTePu inverse rendering with the geometry model
    (label-free), or NSD's pose regressor (``netepu.keypoints.source=regressor``).

    With several species (``models``: one set per species), every subject-frame is inverted
    with each species' model (``<species>/all/``) and takes the species that fits it best
    (:mod:`netepu.pipeline.species_choice`: ``species.csv``, ``<species>/keypoints3d.npz``)."""
    k = cfg.netepu.keypoints
    regress = k.source == "regressor"
    several = len(models) > 1
    settings = {"source": k.source, **{name: k[name] for name in _INVERSE_KEYS}}
    if several and not regress:
        settings["species_steps"] = int(k.species_steps)
    if regress:  # the regressor is trained on the decomposition of the train stage
        settings |= {"label_fraction": k.label_fraction, "regressor_steps": k.regressor_steps}
    else:
        keys = [(m.key_geometry, m.key_initialiser) for m in models]
        settings["geometry"] = [g for g, _ in keys] if several else keys[0][0]
        settings["initialiser"] = [i for _, i in keys] if several else keys[0][1]
        settings["fps"] = cfg.formats.get("fps")  # the travel's time base

    def invert(m: SpeciesModels, export: Path, scene: str, out: Path, **over) -> dict[str, Any]:
        workers = resolve_workers(k.workers, int(cfg.threads), "cpu")  # inverts on the CPU
        if m.initialiser is None:
            log.info("keypoints: no learned initialiser (%s); cold starts screen the "
                     "template poses", m.why_initialiser)
        return invert_export(
            export, scene, m.geometry, out, workers=workers, initialiser=m.initialiser,
            fps=settings["fps"], **({name: k[name] for name in _INVERSE_KEYS} | over),
        )

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        scene = up["scene"].summary["path"]
        export = up["export"].folder
        truth = up["scene"].summary["ground_truth"]
        if regress:
            summary = _regress_keypoints(cfg, scene, _checkpoint(up), export, out)
        elif not several:
            summary = invert(models[0], export, scene, out)
        else:
            return _keypoints_of_species(models, invert, export, scene, out, truth,
                                         int(k.species_steps))
        if truth:
            summary["accuracy"] = keypoint_error(export, scene, out / "keypoints3d.npz")
        return summary

    return Stage(
        "keypoints",
        run,
        settings,
        needs=("scene", "train", "export") if regress else ("scene", "export"),
        enabled=regress or all(m.geometry is not None for m in models),
        why_disabled=f"no geometry model ({models[0].why_geometry}) and source=inverse",
    )


def _keypoints_of_species(models: list[SpeciesModels], invert, export: Path, scene: str,
                          out: Path, truth: bool, species_steps: int) -> dict[str, Any]:
    """The keypoints stage of a run of several species (:func:`keypoints_stage`): every
    subject-frame fitted with each body, ``species_steps`` Adam steps (0: the full fit), to
    choose its species; with short fits, then the full fit of the chosen body alone."""
    fits, per_species = {}, {}
    short = {"steps": species_steps, "init_steps": species_steps} if species_steps else {}
    for m in models:
        log.info("keypoints: every subject fitted with the %s model%s", m.species,
                 f" ({species_steps} steps, to choose its species)" if short else "")
        per_species[m.species] = invert(m, export, scene, out / m.species / "all", **short)
        fits[m.species] = out / m.species / "all" / "keypoints3d.npz"
    choices = choose_species(fits, tracklets=read_tracklets(export))
    write_species_csv(out / "species.csv", choices)
    if not short:
        kept = split_fits(fits, choices, {s: out / s / "keypoints3d.npz" for s in fits})
    else:  # the chosen body's full fit: the one it gets among all subject-frames
        kept, chosen = {}, {}
        for m in models:
            mine = {(c.frame, c.subject_id) for c in choices if c.species == m.species}
            chosen[m.species] = invert(m, export, scene, out / m.species, only=mine)
            kept[m.species] = len(mine)
    log.info("keypoints: subject-frames by species %s (%s/<species>/keypoints3d.npz)",
             kept, out)
    summary: dict[str, Any] = {"species": kept, "fitted": per_species}
    if short:
        summary["chosen"] = chosen
    if truth:
        # the fitted frames' rows decoded and matched once, for every body's file
        matched = subject_truth(export, scene, {c.frame for c in choices})
        summary["species_accuracy"] = species_accuracy(export, scene, choices, matched)
        summary["accuracy"] = {s: keypoint_error(export, scene, out / s / "keypoints3d.npz",
                                                 other_bodies=True, matched=matched)
                               for s in fits}
    return summary


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
    c.threads, c.device = cfg.threads, cfg.device
    c.pose.label_fraction = float(k.label_fraction)
    c.pose.labels = k.get("labels")  # a user's labels instead of the scene's gt/
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


def texture_stage(cfg: DictConfig, models: list[SpeciesModels], have_keypoints: bool) -> Stage:
    """Texture codes, their re-id embeddings and NNOPCS maps of the exported subjects
    (the texture model; netepu.pipeline.embed). With several species, each species' texture
    model codes the subjects that took it (``<species>/``, the keypoints stage's choice)."""
    several = len(models) > 1

    def embed(m: SpeciesModels, up: dict[str, StageResult], out: Path, kp: Path | None):
        res = embed_into_copy(
            up["export"].folder, out, m.texture, kp, up["scene"].summary["path"],
            maps=out / "nnopcs.npz", device=cfg.device,
        )  # fmt: skip
        return {"table": Path(res["path"]).name, "rows": res["rows"], "encoded": res["encoded"],
                "maps": "nnopcs.npz"}

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        kp = up["keypoints"].folder if have_keypoints else None
        if not several:
            return embed(models[0], up, out, kp / "keypoints3d.npz" if kp else None)
        if kp is None:
            raise ConfigError("texture: a run of several species codes each subject with the "
                              "model of its species, which the keypoints stage chooses; it "
                              "did not run")
        return {m.species: embed(m, up, out / m.species, kp / m.species / "keypoints3d.npz")
                for m in models}

    return Stage(
        "texture",
        run,
        {"texture": [m.key_texture for m in models] if several else models[0].key_texture},
        needs=("scene", "export", "keypoints"),
        enabled=all(m.texture is not None for m in models),
        why_disabled=f"no texture model ({models[0].why_texture})",
    )


def identities_stage(cfg: DictConfig, have_texture: bool, ground_truth: bool,
                     species: list[str] | None = None) -> Stage:
    """Identities of the rows from their texture codes (NSD's appearance vectors without a
    texture stage), netepu.reid.identities. With several ``species`` (the texture stage's
    folders), each species' rows are assigned among themselves, their identities numbered
    after the species before (sorted names), and ``species.csv`` of the keypoints stage says
    which rows are which."""
    i = cfg.netepu.identities
    column = str(i.column) if have_texture else "app"
    several = bool(species) and len(species) > 1 and have_texture

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        keys = ["id", "camera", "frame", "subject_id"]
        rig = read_calibration(up["scene"].summary["path"], cfg.train.data.units)
        export = up["export"].folder

        @functools.cache
        def centroids() -> dict:  # every mask decoded once, for motion and positions.csv
            return mask_centroids(json.loads((export / "subjects.coco.json").read_text()))

        motion = _motion(export, rig, column, i, cfg.train.inference.resolution, centroids)
        if not several:
            source = up["texture"].folder if have_texture else up["export"].folder
            table, identity, summary = _assign(source, None, column, i, int(i.k), motion)
        else:
            table, identity, summary = _identities_of_species(up, species, column, i, motion)
            if int(i.k) > 0:
                log.warning("identities: netepu.identities.k=%d is not used with several "
                            "species: each species takes its own count", int(i.k))
        table = {c: table[c] for c in keys}
        write_identities(out / "identities.csv",
                         {**{c: table[c].tolist() for c in keys}, "identity": identity.tolist()})
        by_row = dict(zip(table["id"].tolist(), identity.tolist(), strict=True))
        positions = triangulate_positions(export, rig, by_row, centroids=centroids())
        write_positions(out / "positions.csv", positions)
        write_identity_tracks(up["export"].folder, by_row, out / "tracks", positions)
        summary["column"] = column
        if ground_truth:
            export, scene = up["export"].folder, up["scene"].summary["path"]
            summary["accuracy"] = identity_accuracy_by_contact(
                export, scene, table, identity, _train_size(cfg))
            summary["tracking"] = {  # MOT metrics of the per-camera tracks, then of identities
                "tracks": tracking_metrics(export, scene),
                "identities": tracking_metrics(
                    export, scene, {a: i for a, i in by_row.items() if i >= 0}),
            }
        return summary

    return Stage(
        "identities",
        run,
        {**_container(i), "column": column, **({"species": species} if several else {})},
        needs=("scene", "export", "keypoints", "texture") if several else (
            "scene", "export", "texture"),
        enabled=bool(i.enabled),
        why_disabled="netepu.identities.enabled=false",
    )


def _motion(export: Path, rig: CameraRig, column: str, i: DictConfig, resolution: int,
            centroids: Callable[[], dict] | None = None
            ) -> tuple[Callable[[], dict], float] | None:
    """What ``method=motion`` needs where it may be used (``netepu.identities.method`` motion
    or auto), else None: a function giving the export's subject-frames'
    world positions ((frame, subject_id) -> (3,); every mask decoded, once, and only if
    asked; ``centroids`` gives the export's mask centroids if they are shared) and
    ``netepu.identities.jump`` in world units (``auto``: the tracker's ``position_scale``
    rule on the hull's grid of ``resolution``).

    Raises:
        ConfigError: ``method=motion`` and no subject seen by two cameras.
    """
    method = str(i.method)
    if method not in ("motion", "auto"):
        return None

    @functools.cache
    def positions() -> dict:
        return {key: p for key, (p, _) in triangulate_positions(
            export, rig, centroids=centroids() if centroids is not None else None).items()}

    if method == "motion" and not positions():  # asked for: checked before it is used
        raise ConfigError(f"netepu.identities.method=motion needs subjects seen by two or "
                          f"more cameras (world positions); the export {export} has none: "
                          "use method=tracks or auto")
    return positions, position_scale(i.jump, rig, int(resolution))


def _assign(source: Path, rows: set[int] | None, column: str, i: DictConfig, k: int,
            motion: tuple[Callable[[], dict], float] | None = None
            ) -> tuple[dict, np.ndarray, dict]:
    """The identities (``netepu.identities`` = ``i``, ``k`` of them or 0: the median count) of
    the rows of the embedding table at ``source`` (those of ids ``rows`` only, if given), with
    ``motion`` (:func:`_motion`) where ``motion`` may be taken: ``(table, identity,
    summary)``."""
    keys = ["id", "camera", "frame", "subject_id"]
    by_app = column != "app" and str(i.fill) == "app"
    table = read_embeddings(source, [*keys, column, *(["app"] if by_app else [])],
                            optional=("tracklet_id",))  # an older export has none
    if rows is not None:
        keep = np.isin(np.asarray(table["id"], np.int64), sorted(rows))
        table = {c: v[keep] for c, v in table.items()}
    method = str(i.method)
    by_vectors = method == "auto" and column == "app"
    if by_vectors:
        # NSD's appearance vectors tell individuals apart too little for code_separation to
        # choose by (0.65-1.12 for groups of one texture, 0.83-1.64 for distinct ones:
        # docs/benchmarks/code_separation.md), and less well than where they go: identity
        # 0.40-0.82 by them against 0.79-1.00 by motion on 10 contact runs, distinct
        # textures or not (docs/pipeline.md "Without a texture model"); the subjects by
        # them only where no subject has a position
        method = "motion" if motion is not None and motion[0]() else "subjects"
    positions, jump = motion if motion is not None else (None, 0.0)
    identity, summary = assign_identities(  # rows without a code hold NaN
        table, column, k, method, int(i.restarts),
        "nearest" if by_app else str(i.fill),  # by_app: replaced just below
        positions, jump,
    )
    summary["fill"] = str(i.fill)
    if by_vectors:
        summary["chosen_by"] = "auto: no texture codes"
        log.info("identities: no texture codes: %s", "from where the subjects go "
                 "(method=motion; netepu.identities.method=subjects takes NSD's appearance "
                 "vectors)" if method == "motion" else "NSD's appearance vectors (no subject "
                 "seen by two cameras)")
    if summary.get("chosen_by") == "auto" and summary["method"] in ("motion", "tracks"):
        log.warning(
            "identities: the texture codes of %s do not tell the individuals apart (the two "
            "closest subjects of a frame lie %.2f times as far apart as one subject's codes "
            "move over %d frames; %g or more is needed): the identities come from where the "
            "subjects go (%s), which fails where individuals that look alike stay merged "
            "for long; netepu.identities.method=subjects forces the codes", source,
            summary["separation"], SEPARATION_GAP, SEPARATION_MIN,
            "tracks cut where they jump, stitched by position" if summary["method"] ==
            "motion" else "each row its track's; no positions: tracks can swap individuals "
            "where they touch")
    if by_app and summary["method"] != "motion":  # rows without a code: by their app vector
        coded = ~np.isnan(np.asarray(table[column], np.float64)).any(1)
        identity = transfer_identities(table, identity, coded, "app")
        summary["fill"] = "app: nearest identity by appearance vector"
    return table, identity, summary


def look_alike(summary: dict[str, Any]) -> dict[str, float]:
    """The tables of an identities stage's ``summary`` whose identities ``auto`` took from
    where the subjects go (``motion``, or ``tracks`` without positions) because the codes do
    not tell the individuals apart: table ("" the run's one table, else the species) -> code
    separation.

    Example:
        >>> look_alike({"method": "motion", "chosen_by": "auto", "separation": 0.8})
        {'': 0.8}
        >>> look_alike({"species": {"biped": {"method": "subjects", "chosen_by": "auto",
        ...     "separation": 9.0}, "quadruped": {"method": "tracks", "chosen_by": "auto",
        ...     "separation": 1.1}}})
        {'quadruped': 1.1}
    """
    tables = summary.get("species") or {"": summary}
    return {name: float(t["separation"]) for name, t in tables.items()
            if t.get("chosen_by") == "auto" and t.get("method") in ("motion", "tracks")}


def _identities_of_species(up: dict[str, StageResult], species: list[str], column: str,
                           i: DictConfig,
                           motion: tuple[Callable[[], dict], float] | None = None
                           ) -> tuple[dict, np.ndarray, dict]:
    """Identities of a run of several species: every row takes a species
    (:func:`netepu.pipeline.species_choice.species_of_rows`, from the keypoints stage's
    ``species.csv``), and each species' rows are assigned among themselves from the texture
    stage's ``<species>/`` table (:func:`_assign`, as many identities as the species shows at
    once), numbered after the species before. Returns the whole table's keys, the identities
    (-1: a row of no species) and the summary with one entry per species."""
    keys = ["id", "camera", "frame", "subject_id"]
    choices = read_species_csv(up["keypoints"].folder / "species.csv")
    table = read_embeddings(up["export"].folder, keys, optional=("tracklet_id",))
    of_row = species_of_rows(table["subject_id"], table["frame"], choices,
                             table.get("tracklet_id"))
    identity = np.full(len(of_row), -1, np.int64)
    row = {int(r): n for n, r in enumerate(table["id"].tolist())}
    summary: dict[str, Any] = {"species": {}}
    offset = 0
    for s in sorted(species):
        ids_of_s = {int(r) for r, x in zip(table["id"].tolist(), of_row, strict=True) if x == s}
        if not ids_of_s:
            summary["species"][s] = {"rows": 0}
            continue
        sub, ident, part = _assign(up["texture"].folder / s, ids_of_s, column, i, 0, motion)
        at = np.array([row[int(r)] for r in sub["id"].tolist()], np.int64)
        identity[at] = np.where(ident >= 0, ident + offset, -1)
        summary["species"][s] = part | {"rows": len(at), "first_identity": offset}
        offset += int(ident.max()) + 1 if (ident >= 0).any() else 0
        summary |= {k: v for k, v in part.items() if k in ("method", "fill")}
    summary["identities"] = len(set(identity[identity >= 0].tolist()))
    return table, identity, summary


def _keypoint_file(folder: Path, species: str) -> KeypointFile:
    """The keypoints stage's ``keypoints3d.npz`` in ``folder`` on the skeleton of
    ``species``: its keypoint names and bones where the keypoints are that species' (the
    regressor's keypoints follow the labels it was given), else ``kp0``..."""
    path = folder / "keypoints3d.npz"
    if species not in SPECIES_BODIES:
        return KeypointFile(path, species or "subject")
    body = get_species(species)
    with np.load(path) as z:
        k = z["keypoints"].shape[1] if z["keypoints"].ndim == 3 else 0
    if k != body.num_keypoints:
        return KeypointFile(path, species)
    return KeypointFile(path, species, body.keypoint_names, body.skeleton)


def formats_stage(cfg: DictConfig, have_identities: bool, keypoints: list[str]) -> Stage:
    """The export in the pose tools' files (nsd.export.pose_tools): SLEAP, NWB, DeepLabCut,
    TRC and C3D, under the final identities (the per-camera tracks when the identities
    stage did not run) and with the 3D keypoints of the keypoints stage, on the skeleton of
    each species of ``keypoints`` (empty: the stage did not run; "" a species unknown)."""
    f = cfg.formats

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        export, scene = up["export"].folder, up["scene"].summary["path"]
        rig = read_calibration(scene, cfg.train.data.units)
        row_ids = positions = None
        if have_identities:
            row_ids = identity_by_row(up["identities"].folder / "identities.csv")
            positions = read_positions(up["identities"].folder / "positions.csv")
        else:
            positions = triangulate_positions(export, rig)
        folder = up["keypoints"].folder
        kp = [_keypoint_file(folder / s if len(keypoints) > 1 else folder, s)
              for s in keypoints]
        return write_pose_tool_files(export, scene, rig, out, row_ids, positions, kp,
                                     tuple(f.which), f.fps)

    return Stage("formats", run,
                 {**_container(f), "identities": have_identities, "keypoints": keypoints},
                 needs=("scene", "export", "keypoints", "identities"),
                 enabled=bool(f.enabled) and len(f.which) > 0,
                 why_disabled="formats.enabled=false or formats.which=[]")


def _told_individuals(checkpoint: Path) -> int | None:
    """The individuals the decomposition was told there are: its windows (as trained, after
    ``num_windows: auto`` was settled), or None where they were an upper bound (presence)."""
    model = (load_checkpoint(checkpoint).get("config") or {}).get("model", {})
    if model.get("detector", {}).get("presence") or "num_windows" not in model:
        return None
    return int(model["num_windows"])


def quality_stage(cfg: DictConfig, have_identities: bool) -> Stage:
    """A label-free quality report of the export (nsd.evaluation.quality): how much of the
    moving foreground the masks explain, whether the other cameras confirm them, how stable
    the identities are, with image grids of the worst frames; its warnings go to the log."""
    q = cfg.quality

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        export, scene = up["export"].folder, up["scene"].summary["path"]
        known = _told_individuals(_checkpoint(up))
        ids = identity_by_row(up["identities"].folder / "identities.csv") if have_identities \
            else None
        w, h = cfg.train.data.image_size
        pp = cfg.train.prior_proposal
        report = quality_report(export, scene, (int(w), int(h)), ids,
                                str(cfg.train.data.background), str(cfg.train.data.units),
                                int(q.max_frames), known, int(pp.resolution), pp.min_views)
        alike = look_alike(up["identities"].summary) if have_identities else {}
        if alike:  # the identity figures cannot see swaps of individuals the codes confuse
            report.warnings.append(
                "identities come from where the subjects go: the texture codes do not tell the "
                "individuals apart (code separation " + ", ".join(
                    f"{name + ' ' if name else ''}{sep:.2f}" for name, sep in alike.items())
                + f" < {SEPARATION_MIN:g}); individuals that look alike and stay merged for "
                "long can leave with each other's identities, and identity_switches and "
                "view_agreement cannot show it")
        for warning in report.warnings:
            log.warning("quality: %s", warning)
        worst = report.worst(int(q.worst))
        files = write_grids(export, scene, out / "worst", len(worst), int(cfg.grids.size),
                            only=worst)
        record = report.to_json()
        atomic_write_text(out / "quality.json", json.dumps(record, indent=2))
        atomic_write_text(out / "quality.md", quality_markdown(report, worst))
        return {"summary": record["summary"], "warnings": report.warnings, "worst": worst,
                "files": [f.name for f in files]}

    return Stage("quality", run, {**_container(q), "identities": have_identities,
                                  "grid_size": cfg.grids.size,
                                  "hull": [int(cfg.train.prior_proposal.resolution),
                                           _container(cfg.train.prior_proposal.min_views)]},
                 needs=("scene", "train", "export", "identities"), enabled=bool(q.enabled),
                 why_disabled="quality.enabled=false")


def overlays_stage(cfg: DictConfig, have_identities: bool) -> Stage:
    """A video per camera with the subjects drawn (nsd.export.overlay), coloured and labelled
    by their identity (by their track when the identities stage did not run)."""
    o = cfg.overlays

    def run(out: Path, up: dict[str, StageResult]) -> dict[str, Any]:
        row_ids = None
        if have_identities:
            row_ids = identity_by_row(up["identities"].folder / "identities.csv")
        return write_overlay_videos(up["export"].folder, up["scene"].summary["path"], out,
                                    row_ids, int(o.size), float(o.fps))

    return Stage("overlays", run, {**_container(o), "identities": have_identities},
                 needs=("scene", "export", "identities"), enabled=bool(o.enabled),
                 why_disabled="overlays.enabled=false")


def grids_stage(cfg: DictConfig) -> Stage:
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
