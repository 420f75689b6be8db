"""``nsd-export``: per-subject results of a trained decomposition, in the formats the field reads.

Given a checkpoint and a scene folder, every selected frame is decomposed
(:func:`nsd.inference.multiview.decompose_views`, at the checkpoint's training resolution;
by default each instant's windows are fused with the visual hull of its cameras,
``inference.views=single`` decomposes each image alone), its windows get
cross-view subject ids (:func:`nsd.inference.single.associate_views` with the model's
association score) and the subjects are linked over time
(:class:`nsd.inference.tracking.SubjectTracker`). The export folder then holds (see
``datasets/export.md`` for every field and unit)::

    <out>/
      subjects.coco.json    # COCO dataset: images (camera-frames), one annotation per subject
      crops/                # index.csv + crops-NNNNNN.npz (crops and crop masks)
      embeddings.parquet    # one row per subject-camera-frame with the appearance vector
      tracks/<camera>.txt   # MOTChallenge tracks, one file per camera
      tensorboard/          # projector: a sample of the vectors with crop thumbnails
      tsne.png              # t-SNE of the same sample coloured by subject id
      manifest.json         # version, checkpoint, config, scene, counts, checksums

Streaming: frames are decoded one at a time and decomposed ``batch_size``
instants at a time (by ``workers`` processes, :mod:`nsd.core.processes`); COCO entries,
crops, embedding rows and MOT lines are written in frame order as they are produced, so
memory does not grow with the footage's length (the projector and t-SNE use a bounded
random sample).

Atomicity: the folder is built under a hidden temporary name next to ``out``
and renamed into place at the end. An interrupted export (Ctrl-C, SIGTERM, a
killed process) leaves no folder under the final name; its hidden
``.<name>.partial-<pid>-*`` folder is removed by the next export to the same
place. Re-running always starts from scratch and, with ``overwrite=true`` (the
default), replaces the previous export only once the new one is complete.

COCO image ids: those of the scene's ground truth (``gt/coco.json``) when it
has one, so that ``COCOeval`` scores the export directly; otherwise
``frame * C + c + 1`` with ``C`` the number of cameras in the calibration file
and ``c`` the camera's position in it (the rule the synthetic world uses).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from nsd.core.atomic import atomic_directory, atomic_write_text
from nsd.core.processes import BatchPool, resolve_workers
from nsd.core.threads import available_cores, set_threads
from nsd.export.config import check_export_config
from nsd.export.inputs import ExportInputs, prepare_inputs
from nsd.export.manifest import Timing, build_manifest, share_folder, toolkit_version
from nsd.export.writer import SubjectWriter
from nsd.inference.multiview import InferenceSettings
from nsd.io.embedding_views import plot_tsne, write_projector
from nsd.io.frame_selection import iter_selected

log = logging.getLogger(__name__)

__all__ = ["ExportSummary", "export_subjects", "run"]


@dataclass
class ExportSummary:
    """What an export wrote (the same figures are in ``manifest.json``).

    Attributes:
        out: the export folder.
        frames: instants exported (each with all selected cameras).
        camera_frames: frames x cameras.
        subjects: COCO annotations (subject-camera-frames).
        tracks: distinct subject ids.
        seconds: wall time of the streaming pass (decode, decompose, write).
        workers: processes that decomposed the batches (``workers``).
        manifest: the manifest's content.
    """

    out: Path
    frames: int
    camera_frames: int
    subjects: int
    tracks: int
    seconds: float
    workers: int = 1
    manifest: dict[str, Any] = field(repr=False, default_factory=dict)


def export_subjects(cfg: DictConfig) -> ExportSummary:
    """Export a scene's subjects as configured (``conf/export.yaml``; see the module).

    Raises:
        CheckpointError: the checkpoint is missing, unusable, or the scene has
            cameras it was not trained with.
        FootageError: the scene, a video or a frame cannot be read (the message
            names the camera, file and frame).
        ConfigError: a setting is out of range (the message names the key).
        FileExistsError: ``out`` exists and ``overwrite`` is false.
    """
    check_export_config(cfg)
    ckpt = Path(cfg.checkpoint)
    out = Path(cfg.out) if cfg.out else (ckpt if ckpt.is_dir() else ckpt.parent) / "export"
    if out.exists() and not cfg.overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=true to replace it")
    inp = prepare_inputs(cfg)
    device = next(inp.trained.model.parameters()).device.type
    workers = resolve_workers(cfg.workers, int(cfg.threads), device)
    asked = InferenceSettings.from_config(cfg.get("inference"))
    used = asked.for_views(len(inp.footage.rig))
    if used != asked:
        log.warning("one camera exported: single-image inference (inference.views=single)")
        OmegaConf.update(cfg, "inference.views", used.views, force_add=True)  # for the manifest
    with atomic_directory(out, overwrite=bool(cfg.overwrite)) as tmp:
        writer = SubjectWriter(inp, cfg, tmp)
        t0 = time.perf_counter()
        worker_peak = _stream(writer, inp, cfg, workers)
        created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        writer.close(
            {
                "description": f"nsd-export of {inp.scene.name}",
                "version": toolkit_version(),
                "date_created": created,
                "checkpoint": str(inp.trained.path.resolve()),
            }
        )
        seconds = time.perf_counter() - t0
        t1 = time.perf_counter()
        views_written = _write_views(writer, cfg, tmp)
        timing = Timing(seconds, time.perf_counter() - t1, workers, worker_peak)
        manifest = build_manifest(cfg, inp, writer, tmp, created, views_written, timing)
        atomic_write_text(tmp / "manifest.json", json.dumps(manifest, indent=2, default=str))
        share_folder(tmp)
    counts = manifest["counts"]
    return ExportSummary(
        out,
        counts["frames"],
        counts["camera_frames"],
        counts["subjects"],
        counts["tracks"],
        seconds,
        workers,
        manifest,
    )


def _batches(inp: ExportInputs, size: int,
             decode: bool) -> Iterator[list[tuple[int, list[np.ndarray] | None]]]:
    """The selected frames, ``size`` instants per batch: decoded here one instant at a time,
    or (``decode`` false: image files, read by whoever decomposes the batch) as indices."""
    selected = (iter_selected(inp.footage, inp.frames) if decode
                else ((int(t), None) for t in inp.frames))
    items: list[tuple[int, list[np.ndarray] | None]] = []
    for t, views in selected:
        items.append((t, views))
        if len(items) == size:
            yield items
            items = []
    if items:
        yield items


def _stream(writer: SubjectWriter, inp: ExportInputs, cfg: DictConfig, workers: int) -> float:
    """Decompose the batches (``workers`` processes) and write them in order; returns the
    largest peak resident size of one worker in MiB (0 without workers)."""
    bar = tqdm(
        total=len(inp.frames),
        unit="frame",
        desc="export",
        dynamic_ncols=True,
        disable=not cfg.progress,
    )
    threads = int(cfg.threads) or available_cores()
    track = writer.hull_track(inp.frames)  # the hull's clustering through every batch, in order

    def jobs(batches: Iterator[list]) -> Iterator[tuple[list, list | None, bool]]:
        for items in batches:
            # the k-means alone (a scene without the mixture) needs no other instant: each
            # batch's worker clusters its own, and the parent only writes
            clusters = writer.hull_clusters(items, track) if track.mixture else None
            yield items, clusters, track.mixture

    with BatchPool(lambda job: writer.decompose(*job), workers, threads) as pool:
        decode = workers == 1 or not inp.footage.random_access  # else the workers read files
        batches = _batches(inp, int(cfg.batch_size), decode)
        for (items, *_), results in pool.map(jobs(batches)):
            writer.write(results)
            bar.update(len(items))
    bar.close()
    return pool.worker_peak_mb


def _write_views(writer: SubjectWriter, cfg: DictConfig, root: Path) -> dict[str, bool]:
    """The TensorBoard projector and the t-SNE figure of the sampled vectors, as configured."""
    written = {"tensorboard": False, "tsne": False}
    if cfg.views.tensorboard and len(writer.sample):
        write_projector(writer.sample, root / "tensorboard")
        written["tensorboard"] = True
    if cfg.views.tsne:
        written["tsne"] = plot_tsne(
            writer.sample, root / "tsne.png", float(cfg.views.perplexity), int(cfg.views.seed)
        )
    return written


def run(cfg: DictConfig) -> ExportSummary:
    """:func:`export_subjects` with ``cfg.threads`` torch threads; prints a one-line summary."""
    set_threads(int(cfg.threads))
    s = export_subjects(cfg)
    print(
        f"exported {s.frames} frames ({s.camera_frames} camera-frames, {s.subjects} subjects, "
        f"{s.tracks} tracks) to {s.out} in {s.seconds:.1f} s "
        f"({s.frames / max(s.seconds, 1e-9):.1f} frames/s, {s.workers} worker"
        f"{'s' if s.workers > 1 else ''})"
    )
    return s
