"""The export's ``manifest.json``: what was exported, from what, by which version, and checksums.

``FORMAT`` names the layout of the export folder (``datasets/export.md``); a reader
checks it before it reads anything else.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

import nsd

__all__ = ["FORMAT", "Timing", "build_manifest", "sha256_file", "share_folder", "toolkit_version"]


FORMAT = "nsd-export/1"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def share_folder(root: Path) -> None:
    """Give the folder the permissions of a plain ``mkdir``/``open`` under the umask.

    The atomic writers create private temporaries (0700 folders, 0600 files);
    an export is meant to be read by other tools and users.
    """
    umask = os.umask(0)
    os.umask(umask)
    for p in [root, *root.rglob("*")]:
        p.chmod((0o777 if p.is_dir() else 0o666) & ~umask)


def toolkit_version() -> str:
    try:
        return version("nsd-netepu")
    except Exception:
        return nsd.__version__


def _selection(spec: Any) -> Any:
    return OmegaConf.to_container(spec) if OmegaConf.is_config(spec) else spec


@dataclass(frozen=True)
class Timing:
    """Wall times of an export: the streaming pass and the embedding views (seconds); the
    processes that decomposed the batches and the largest peak resident size of one (MiB,
    0 without workers)."""

    seconds: float
    views_seconds: float
    workers: int = 1
    worker_peak_mb: float = 0.0


def build_manifest(
    cfg: DictConfig,
    inputs: Any,
    writer: Any,
    root: Path,
    created: str,
    views_written: dict[str, bool],
    timing: Timing,
) -> dict[str, Any]:
    """The manifest of the finished folder ``root`` (every file is read for its checksum).

    Args:
        cfg: the export config as run.
        inputs: the :class:`nsd.export.inputs.ExportInputs` that were exported.
        writer: the closed :class:`nsd.export.writer.SubjectWriter`.
        root: the folder whose files the manifest lists (before it is renamed into place).
        created: ISO date of the export.
        views_written: which embedding views were written (``tensorboard``, ``tsne``).
        timing: wall times of the export.
    """
    n_frames = int(writer.frames_done)
    return {
        "format": FORMAT,
        "toolkit": {"name": "nsd-netepu", "version": toolkit_version(), "torch": torch.__version__},
        "created": created,
        "checkpoint": _checkpoint_section(inputs.trained),
        "config": OmegaConf.to_container(cfg, resolve=True),
        "training_config": OmegaConf.to_container(inputs.trained.config, resolve=True),
        "scene": _scene_section(inputs, writer.names),
        "frames": {
            "selection": _selection(cfg.frames),
            "count": n_frames,
            "first": int(inputs.frames[0]),
            "last": int(inputs.frames[-1]),
        },
        "counts": _counts_section(writer),
        "views": views_written,
        "timing": _timing_section(timing, n_frames, len(writer.names)),
        "files": {
            p.relative_to(root).as_posix(): {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
            for p in sorted(root.rglob("*"))
            if p.is_file()
        },
    }


def _checkpoint_section(trained: Any) -> dict[str, Any]:
    return {
        "path": str(trained.path.resolve()),
        "sha256": sha256_file(trained.path),
        "step": trained.step,
        "cameras": trained.cameras,
        "image_size": list(trained.frame_hw),
    }


def _scene_section(inputs: Any, names: list[str]) -> dict[str, Any]:
    footage = inputs.footage
    return {
        "path": str(inputs.scene.resolve()),
        "cameras": names,
        "native_sizes": {c: list(footage.native_rig[v].size) for v, c in enumerate(names)},
        "num_frames": footage.num_frames,
        "ground_truth": (inputs.scene / "gt" / "coco.json").is_file(),
    }


def _counts_section(writer: Any) -> dict[str, Any]:
    n_frames = int(writer.frames_done)
    return {
        "frames": n_frames,
        "camera_frames": n_frames * len(writer.names),
        "subjects": writer.coco.num_annotations,
        "tracks": writer.tracker.next_id - 1,
        "crops": writer.crops.count,
        "crop_files": writer.crops.files,
        "embedding_rows": writer.embeddings.rows,
        "mot_lines": dict(writer.mot.counts),
        "sample": len(writer.sample),
    }


def _timing_section(timing: Timing, n_frames: int, V: int) -> dict[str, float]:
    return {
        "seconds": round(timing.seconds, 3),
        "frames_per_second": round(n_frames / max(timing.seconds, 1e-9), 3),
        "camera_frames_per_second": round(n_frames * V / max(timing.seconds, 1e-9), 3),
        "views_seconds": round(timing.views_seconds, 3),
        "workers": timing.workers,
        "worker_peak_rss_mb": round(timing.worker_peak_mb, 1),
    }
