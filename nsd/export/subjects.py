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
instants at a time; COCO entries, crops, embedding rows and MOT lines are
written as they are produced, so memory does not grow with the footage's length
(the projector and t-SNE use a bounded random sample).

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

import ctypes
import datetime as _dt
import functools
import hashlib
import json
import logging
import os
import signal
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from importlib.metadata import version
from importlib.resources import files
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from pycocotools import mask as mask_utils
from tqdm import tqdm

import nsd
from nsd.cameras.calibration_io import read_calibration
from nsd.core.atomic import atomic_directory, atomic_write_text
from nsd.core.errors import ConfigError, FootageError, NSDError
from nsd.inference.association_scores import association_scores
from nsd.inference.multiview import InferenceSettings, decompose_views
from nsd.inference.single import associate_views
from nsd.inference.tracking import SubjectObservation, SubjectTracker
from nsd.io.coco import CocoStreamWriter
from nsd.io.coco_results import SUBJECT_CATEGORY, decomposition_to_coco
from nsd.io.crops import CropWriter
from nsd.io.embedding_views import Reservoir, plot_tsne, write_projector
from nsd.io.embeddings import EmbeddingWriter
from nsd.io.footage import ImageFolderSource, MultiViewFootage
from nsd.io.frame_selection import iter_selected, select_frames
from nsd.io.mot import MotWriter
from nsd.io.scenes import resolve_scene
from nsd.model.checkpoint import TrainedDecomposition, load_decomposition

log = logging.getLogger(__name__)

__all__ = ["ExportSummary", "export_subjects", "load_export_config", "main", "run"]

FORMAT = "nsd-export/1"
CATEGORIES = [{"id": SUBJECT_CATEGORY, "name": "subject", "supercategory": "subject"}]
_CLI_ONLY = ("defaults", "hydra")


def load_export_config(**overrides: Any) -> DictConfig:
    """The shipped ``conf/export.yaml`` with top-level or dotted-key overrides.

    Example:
        >>> cfg = load_export_config(checkpoint="run", **{"crop.size": 32})
        >>> cfg.crop.size, cfg.batch_size
        (32, 8)
    """
    with (files("nsd.conf") / "export.yaml").open() as f:
        cfg = OmegaConf.load(f)
    with (files("nsd.conf") / "inference" / "default.yaml").open() as f:
        cfg.inference = OmegaConf.load(f)  # the defaults list's group, as nsd-export composes it
    for key in _CLI_ONLY:
        cfg.pop(key, None)
    for key, value in overrides.items():
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if not OmegaConf.is_dict(node) or leaf not in node.keys():
            raise ConfigError(f"export config has no key {key!r}")
        OmegaConf.update(cfg, key, value, merge=False)
    return cfg


def _check_config(cfg: DictConfig) -> None:
    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise ConfigError(f"{key}: {what}, got {OmegaConf.select(cfg, key)!r}")

    need(
        OmegaConf.select(cfg, "checkpoint", throw_on_missing=False) not in (None, "???"),
        "checkpoint",
        "give the checkpoint.pt of nsd-train (checkpoint=...)",
    )
    need(int(cfg.batch_size) >= 1, "batch_size", "must be >= 1")
    need(0 < float(cfg.threshold) < 1, "threshold", "must be in (0, 1)")
    need(cfg.refine in ("residual", "none"), "refine", "must be residual or none")
    InferenceSettings.from_config(cfg.get("inference"))  # a clear error naming the key
    need(int(cfg.crop.size) >= 4, "crop.size", "must be >= 4 pixels")
    need(float(cfg.crop.margin) >= 0, "crop.margin", "must be >= 0")
    need(int(cfg.crop.chunk) >= 1, "crop.chunk", "must be >= 1")
    need(cfg.embeddings.format in ("parquet", "npz"), "embeddings.format", "parquet or npz")
    need(int(cfg.embeddings.row_group_size) >= 1, "embeddings.row_group_size", "must be >= 1")
    need(0 <= float(cfg.tracking.appearance_weight) <= 1, "tracking.appearance_weight", "in [0, 1]")
    need(int(cfg.tracking.max_gap) >= 0, "tracking.max_gap", "must be >= 0")
    need(int(cfg.views.max_points) >= 1, "views.max_points", "must be >= 1")
    need(int(cfg.views.thumbnail) >= 4, "views.thumbnail", "must be >= 4 pixels")


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
        manifest: the manifest's content.
    """

    out: Path
    frames: int
    camera_frames: int
    subjects: int
    tracks: int
    seconds: float
    manifest: dict[str, Any] = field(repr=False, default_factory=dict)


@dataclass
class _Inputs:
    """The scene as the export sees it."""

    trained: TrainedDecomposition
    footage: MultiViewFootage  # at the training size: rig, backgrounds; sources are native
    scene: Path
    frames: np.ndarray
    images: _ImageEntries  # (view, frame) -> COCO image entry
    backgrounds: torch.Tensor  # (V, 3, H, W) in [0, 1]
    cameras: dict[str, torch.Tensor]  # stacked K, R, t, dist at the training size


class _ImageEntries:
    """COCO image entries of camera-frames (see the module docstring for the ids).

    With ground truth, its image table (the selected entries) is kept; otherwise
    entries are computed when asked, so nothing here grows with the footage.
    """

    def __init__(self, footage: MultiViewFootage, scene: Path, frames: np.ndarray) -> None:
        self.footage, self.scene = footage, scene
        self.gt: dict[tuple[str, int], dict] | None = None
        gt_file = scene / "gt" / "coco.json"
        if gt_file.is_file():
            wanted = {(c, int(t)) for c in footage.camera_names for t in frames}
            images = json.loads(gt_file.read_text())["images"]  # the rest is freed here
            self.gt = {k: im for im in images if (k := (im["camera"], int(im["frame"]))) in wanted}
            missing = wanted - set(self.gt)
            if missing:
                raise FootageError(
                    f"{gt_file}: no COCO image for camera-frames {sorted(missing)[:5]}; "
                    "the ground truth does not match the footage"
                )
        names = read_calibration(scene).names
        self.index = {c: names.index(c) for c in footage.camera_names}
        self.num_cameras = len(names)

    def __call__(self, v: int, t: int) -> dict:
        cam = self.footage.camera_names[v]
        if self.gt is not None:
            return self.gt[(cam, t)]
        src = self.footage.sources[v]
        if isinstance(src, ImageFolderSource):
            name = src.files[t].relative_to(self.scene).as_posix()
        else:
            name = f"{src.path.relative_to(self.scene).as_posix()}#{t:06d}"
        W, H = self.footage.native_rig[v].size
        return {
            "id": t * self.num_cameras + self.index[cam] + 1,
            "file_name": name,
            "width": int(W),
            "height": int(H),
            "camera": cam,
            "frame": t,
        }


def _prepare(cfg: DictConfig) -> _Inputs:
    trained = load_decomposition(cfg.checkpoint)
    scene = cfg.scene or trained.config.data.get("scene")
    if not scene:
        scene = resolve_scene(None)
    scene = Path(scene).expanduser()
    H, W = trained.image_size
    cameras = list(cfg.cameras) if cfg.cameras is not None else None
    if cameras is None and scene.is_dir():
        trained.check_cameras(read_calibration(scene).names, scene)
    footage = MultiViewFootage(scene, cameras=cameras, image_size=(W, H))
    trained.check_cameras(footage.camera_names, scene)
    frames = select_frames(
        OmegaConf.to_object(cfg.frames) if OmegaConf.is_config(cfg.frames) else cfg.frames,
        footage.num_frames,
    )
    bg = torch.from_numpy(footage.background()).permute(0, 3, 1, 2).float().div_(255.0)
    return _Inputs(
        trained,
        footage,
        scene,
        frames,
        _ImageEntries(footage, scene, frames),
        bg,
        footage.rig.stacked(torch.float32),
    )


def _to_model_size(views: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """Resize native views to the training size (W, H) as MultiViewFootage does: (V, H, W, 3)."""
    return np.stack(
        [
            v
            if (v.shape[1], v.shape[0]) == size
            else cv2.resize(v, size, interpolation=cv2.INTER_AREA)
            for v in views
        ]
    )


@functools.cache
def _malloc_trim():
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


def _trim_heap() -> None:
    """Give freed heap memory back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    Called after every batch: without it, allocator fragmentation lets the
    resident size of a long export creep up for its first ~1,000 frames
    (``docs/benchmarks/export.md``).
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / max(float(np.linalg.norm(x)), 1e-8)


class _Exporter:
    """The writers of one export folder and the per-batch work."""

    def __init__(self, inp: _Inputs, cfg: DictConfig, root: Path) -> None:
        self.inp, self.cfg, self.root = inp, cfg, root
        self.model = inp.trained.model
        self.names = inp.footage.camera_names
        self.dims = int(self.model.cfg.association_dims)
        self.coco = CocoStreamWriter(root / "subjects.coco.json")
        self.crops = CropWriter(root / "crops", int(cfg.crop.size), int(cfg.crop.chunk))
        self.embeddings = EmbeddingWriter(
            root / "embeddings", cfg.embeddings.format, int(cfg.embeddings.row_group_size)
        )
        self.mot = MotWriter(root / "tracks", self.names)
        t = cfg.tracking
        self.tracker = SubjectTracker(
            float(t.appearance_weight), float(t.min_similarity), int(t.max_gap)
        )
        self.sample = Reservoir(int(cfg.views.max_points), int(cfg.views.seed))
        self.inference = InferenceSettings.from_config(cfg.get("inference"))
        self.grid = (
            self.inference.grid(inp.footage.rig, inp.trained.image_size)
            if self.inference.multiview
            else None
        )
        self.frames_done = 0

    def batch(self, items: list[tuple[int, list[np.ndarray]]]) -> None:
        """Decompose and write B instants: ``items`` = [(t, native views)]."""
        V = len(self.names)
        H, W = self.inp.trained.image_size
        small = np.stack([_to_model_size(views, (W, H)) for _, views in items])  # B, V, H, W, 3
        images = torch.from_numpy(small).flatten(0, 1).permute(0, 3, 1, 2).float().div_(255.0)
        bgs = self.inp.backgrounds.repeat(len(items), 1, 1, 1)
        dec = decompose_views(
            self.model,
            images,
            bgs,
            V,
            self.inference,
            self.grid,
            mask_threshold=float(self.cfg.threshold),
            refine=str(self.cfg.refine),
        )
        for b, (t, views) in enumerate(items):
            self._frame(dec, b * V, t, views)
        self.frames_done += len(items)
        del dec, images, bgs, small
        _trim_heap()

    def _frame(self, dec, first: int, t: int, views: list[np.ndarray]) -> None:
        V = len(self.names)
        sl = slice(first, first + V)
        slots = None if dec.slots is None else dec.slots[sl]
        one = SimpleNamespace(windows=dec.windows[sl], app=dec.app[sl], slots=slots)
        H, W = self.inp.trained.image_size
        bonus = self.inference.slot_bonus

        def score(v: int, r: int) -> torch.Tensor:
            return association_scores(self.model, one, self.inp.cameras, (H, W), v, r, bonus)

        assoc = associate_views(dec.app[sl], dec.active[sl], self.dims, score)
        per_view = []
        observed: dict[int, list[tuple[str, np.ndarray, np.ndarray]]] = defaultdict(list)
        for v, cam in enumerate(self.names):
            image = self.inp.images(v, t)
            self.coco.add_image(image)
            native = (int(image["height"]), int(image["width"]))
            res = decomposition_to_coco(
                dec,
                first + v,
                image["id"],
                native,
                float(self.cfg.threshold),
                {"camera": cam, "frame": t},
            )
            per_view.append(res)
            for r in res:
                aid = int(assoc[v, r["slot"]])
                r["association_id"] = aid
                app = dec.app[first + v, r["slot"]].numpy()
                observed[aid].append((cam, np.asarray(r["bbox"]), app))
        subjects = {
            aid: SubjectObservation(
                _unit(np.mean([_unit(a[: self.dims]) for _, _, a in obs], 0)),
                {cam: box for cam, box, _ in obs},
            )
            for aid, obs in observed.items()
        }
        track = self.tracker.update(t, subjects)
        rows: dict[str, list] = defaultdict(list)
        thumb = int(self.cfg.views.thumbnail)
        for v, cam in enumerate(self.names):
            for r in per_view[v]:
                sid = track[r["association_id"]]
                ann_id = self.coco.add_annotation({**r, "subject_id": sid, "iscrowd": 0})
                mask = mask_utils.decode(r["segmentation"]).astype(bool)
                crop, _ = self.crops.add(
                    ann_id, sid, cam, t, views[v], mask, r["bbox"], float(self.cfg.crop.margin)
                )
                self.mot.write(cam, t, sid, r["bbox"], r["score"])
                app = dec.app[first + v, r["slot"]].numpy().astype(np.float32)
                small = cv2.resize(crop, (thumb, thumb), interpolation=cv2.INTER_AREA)
                self.sample.offer(app, small, (sid, cam, t))
                for k, val in (
                    ("id", ann_id),
                    ("subject_id", sid),
                    ("association_id", r["association_id"]),
                    ("camera", cam),
                    ("frame", t),
                    ("image_id", r["image_id"]),
                    ("slot", r["slot"]),
                    ("score", r["score"]),
                    ("depth", r["depth"]),
                    ("bbox_x", r["bbox"][0]),
                    ("bbox_y", r["bbox"][1]),
                    ("bbox_w", r["bbox"][2]),
                    ("bbox_h", r["bbox"][3]),
                    ("area", r["area"]),
                    ("app", app),
                ):
                    rows[k].append(val)
        if rows:
            self.embeddings.write(_columns(rows))

    def close(self, info: dict[str, Any]) -> None:
        D = int(self.model.encoder.app_dims)
        self.coco.close(info, CATEGORIES)
        self.crops.close()
        self.mot.close()
        self.embeddings.close(_columns({k: [] for k in _COLUMN_TYPES}, app_dims=D))


_COLUMN_TYPES = {
    "id": np.int64,
    "subject_id": np.int64,
    "association_id": np.int64,
    "camera": str,
    "frame": np.int64,
    "image_id": np.int64,
    "slot": np.int32,
    "score": np.float32,
    "depth": np.float32,
    "bbox_x": np.float32,
    "bbox_y": np.float32,
    "bbox_w": np.float32,
    "bbox_h": np.float32,
    "area": np.float32,
    "app": np.float32,
}


def _columns(rows: dict[str, list], app_dims: int = 0) -> dict[str, np.ndarray]:
    """Lists of row values -> typed numpy columns (``app`` (n, D))."""
    out = {}
    for k, dtype in _COLUMN_TYPES.items():
        if k == "app":
            vals = rows[k]
            out[k] = np.stack(vals).astype(np.float32) if vals else np.zeros((0, app_dims))
        else:
            out[k] = np.asarray(rows[k], dtype=dtype)
    return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _share(root: Path) -> None:
    """Give the folder the permissions of a plain ``mkdir``/``open`` under the umask.

    The atomic writers create private temporaries (0700 folders, 0600 files);
    an export is meant to be read by other tools and users.
    """
    umask = os.umask(0)
    os.umask(umask)
    for p in [root, *root.rglob("*")]:
        p.chmod((0o777 if p.is_dir() else 0o666) & ~umask)


def _toolkit_version() -> str:
    try:
        return version("nsd-netepu")
    except Exception:
        return nsd.__version__


def _selection(spec: Any) -> Any:
    return OmegaConf.to_container(spec) if OmegaConf.is_config(spec) else spec


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
    _check_config(cfg)
    ckpt = Path(cfg.checkpoint)
    out = Path(cfg.out) if cfg.out else (ckpt if ckpt.is_dir() else ckpt.parent) / "export"
    if out.exists() and not cfg.overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=true to replace it")
    inp = _prepare(cfg)
    trained = inp.trained
    asked = InferenceSettings.from_config(cfg.get("inference"))
    used = asked.for_views(len(inp.footage.rig))
    if used != asked:
        log.warning("one camera exported: single-image inference (inference.views=single)")
        OmegaConf.update(cfg, "inference.views", used.views, force_add=True)  # for the manifest
    with atomic_directory(out, overwrite=bool(cfg.overwrite)) as tmp:
        ex = _Exporter(inp, cfg, tmp)

        bar = tqdm(
            total=len(inp.frames),
            unit="frame",
            desc="export",
            dynamic_ncols=True,
            disable=not cfg.progress,
        )
        t0 = time.perf_counter()
        items: list[tuple[int, list[np.ndarray]]] = []
        for t, views in iter_selected(inp.footage, inp.frames):
            items.append((t, views))
            if len(items) == int(cfg.batch_size):
                ex.batch(items)
                bar.update(len(items))
                items = []
        if items:
            ex.batch(items)
            bar.update(len(items))
        bar.close()
        info = {
            "description": f"nsd-export of {inp.scene.name}",
            "version": _toolkit_version(),
            "date_created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "checkpoint": str(trained.path.resolve()),
        }
        ex.close(info)
        seconds = time.perf_counter() - t0
        t1 = time.perf_counter()
        views_written = {"tensorboard": False, "tsne": False}
        if cfg.views.tensorboard and len(ex.sample):
            write_projector(ex.sample, tmp / "tensorboard")
            views_written["tensorboard"] = True
        if cfg.views.tsne:
            views_written["tsne"] = plot_tsne(
                ex.sample, tmp / "tsne.png", float(cfg.views.perplexity), int(cfg.views.seed)
            )
        views_seconds = time.perf_counter() - t1
        n_frames = int(ex.frames_done)
        V = len(ex.names)
        manifest = {
            "format": FORMAT,
            "toolkit": {
                "name": "nsd-netepu",
                "version": _toolkit_version(),
                "torch": torch.__version__,
            },
            "created": info["date_created"],
            "checkpoint": {
                "path": str(trained.path.resolve()),
                "sha256": _sha256(trained.path),
                "step": trained.step,
                "cameras": trained.cameras,
                "image_size": list(trained.image_size),
            },
            "config": OmegaConf.to_container(cfg, resolve=True),
            "training_config": OmegaConf.to_container(trained.config, resolve=True),
            "scene": {
                "path": str(inp.scene.resolve()),
                "cameras": ex.names,
                "native_sizes": {
                    c: list(inp.footage.native_rig[v].size) for v, c in enumerate(ex.names)
                },
                "num_frames": inp.footage.num_frames,
                "ground_truth": (inp.scene / "gt" / "coco.json").is_file(),
            },
            "frames": {
                "selection": _selection(cfg.frames),
                "count": n_frames,
                "first": int(inp.frames[0]),
                "last": int(inp.frames[-1]),
            },
            "counts": {
                "frames": n_frames,
                "camera_frames": n_frames * V,
                "subjects": ex.coco.num_annotations,
                "tracks": ex.tracker.next_id - 1,
                "crops": ex.crops.count,
                "crop_files": ex.crops.files,
                "embedding_rows": ex.embeddings.rows,
                "mot_lines": dict(ex.mot.counts),
                "sample": len(ex.sample),
            },
            "views": views_written,
            "timing": {
                "seconds": round(seconds, 3),
                "frames_per_second": round(n_frames / max(seconds, 1e-9), 3),
                "camera_frames_per_second": round(n_frames * V / max(seconds, 1e-9), 3),
                "views_seconds": round(views_seconds, 3),
            },
            "files": {
                p.relative_to(tmp).as_posix(): {"bytes": p.stat().st_size, "sha256": _sha256(p)}
                for p in sorted(tmp.rglob("*"))
                if p.is_file()
            },
        }
        atomic_write_text(tmp / "manifest.json", json.dumps(manifest, indent=2, default=str))
        _share(tmp)
    return ExportSummary(
        out,
        n_frames,
        n_frames * V,
        ex.coco.num_annotations,
        ex.tracker.next_id - 1,
        seconds,
        manifest,
    )


def run(cfg: DictConfig) -> ExportSummary:
    """:func:`export_subjects` with ``cfg.threads`` torch threads; prints a one-line summary."""
    torch.set_num_threads(max(1, int(cfg.threads)))
    s = export_subjects(cfg)
    print(
        f"exported {s.frames} frames ({s.camera_frames} camera-frames, {s.subjects} subjects, "
        f"{s.tracks} tracks) to {s.out} in {s.seconds:.1f} s "
        f"({s.frames / max(s.seconds, 1e-9):.1f} frames/s)"
    )
    return s


def _terminate(signum, frame) -> None:
    raise SystemExit(128 + signum)  # unwinds atomic_directory, which removes the partial folder


@hydra.main(config_path="pkg://nsd.conf", config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """Entry point of ``nsd-export``; bad input exits with status 2 and a message."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        run(cfg)
    except (NSDError, FileExistsError) as e:
        print(f"nsd-export: error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
