"""The writers of one export folder and the per-batch work (:class:`SubjectWriter`).

Each batch of instants is decomposed (:meth:`SubjectWriter.decompose`:
:func:`nsd.inference.multiview.decompose_views`, cross-view subject ids, COCO results and crops
of each instant; this part may run in a worker process, :mod:`nsd.core.processes`), then its
subjects get track ids and every subject-camera-frame is written in order
(:meth:`SubjectWriter.write`): a COCO annotation, a crop, a MOT line, a sampled vector and a
table row (:data:`COLUMN_TYPES`; ``datasets/export.md`` lists every column).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig
from pycocotools import mask as mask_utils
from torch import Tensor

from nsd.core.memory import trim_heap
from nsd.cues.clustering import ClusterTrack
from nsd.export.inputs import ExportInputs, ImageEntries, to_model_size
from nsd.export.positions import point_from_views
from nsd.inference.association_scores import association_scores
from nsd.inference.multiview import (
    InferenceSettings,
    carry_hull_track,
    decompose_views,
    model_scene_track,
)
from nsd.inference.single import associate_views
from nsd.inference.tracking import (
    SubjectObservation,
    SubjectTracker,
    max_tracks,
    position_scale,
)
from nsd.io.coco import CocoStreamWriter
from nsd.io.coco_results import SUBJECT_CATEGORY, decomposition_to_coco
from nsd.io.crops import CropWriter, subject_crop
from nsd.io.embedding_views import Reservoir
from nsd.io.embeddings import EmbeddingWriter
from nsd.io.mot import MotWriter
from nsd.ops.vectors import unit_vectors

__all__ = ["CATEGORIES", "COLUMN_TYPES", "FrameResult", "SubjectWriter", "columns"]


JPEG_QUALITY = 95  # frame_images: the exported frames as JPEG of this quality
CATEGORIES = [{"id": SUBJECT_CATEGORY, "name": "subject", "supercategory": "subject"}]


@dataclass
class FrameResult:
    """One instant decomposed, ready to be tracked and written.

    Attributes:
        t: frame index.
        per_view: per camera, its COCO results (native size, with ``association_id``).
        apps: per camera and result, the appearance vector (A,) float32.
        crops: per camera and result, (crop window (x0, y0, side), crop uint8 (S, S, 3),
            crop mask uint8 (S, S), thumbnail uint8 (s, s, 3)).
        observations: per association id, what the tracker links over time.
    """

    t: int
    per_view: list[list[dict]]
    apps: list[list[np.ndarray]]
    crops: list[list[tuple]]
    observations: dict[int, SubjectObservation]


class SubjectWriter:
    """The writers of one export folder and the per-batch work."""

    def __init__(self, inp: ExportInputs, cfg: DictConfig, root: Path) -> None:
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
        self.sample = Reservoir(int(cfg.views.max_points), int(cfg.views.seed))
        self.inference = InferenceSettings.from_config(cfg.get("inference"))
        t = cfg.tracking
        self.tracker = SubjectTracker(
            float(t.appearance_weight), float(t.min_similarity), int(t.max_gap),
            float(t.position_weight),
            position_scale(t.position_scale, inp.footage.rig, int(self.inference.resolution)),
            max_tracks(t.max_tracks, int(self.model.cfg.num_windows)),
        )
        self.grid = (
            self.inference.grid(inp.footage.rig, inp.trained.frame_hw)
            if self.inference.multiview
            else None
        )
        self.frames_done = 0
        self.native_backgrounds = (  # before any worker is forked, which inherits them
            [inp.footage.native_background(v) for v in range(len(self.names))]
            if self._native_refine() else None)

    def batch(self, items: list[tuple[int, list[np.ndarray] | None]]) -> None:
        """Decompose and write B instants: ``items`` = [(t, native views or None)]."""
        self.write(self.decompose(items))

    def write(self, results: list[FrameResult]) -> None:
        """Track and write B decomposed instants, in order (this process only)."""
        for res in results:
            self._write_frame(res)
        self.frames_done += len(results)

    def _read(self, items: list[tuple[int, list[np.ndarray] | None]]
              ) -> tuple[list[tuple[int, list[np.ndarray]]], Tensor, Tensor]:
        """``items`` = [(t, native views or None: read here)] with every view read, and the
        B instants at the model's size (B * V, 3, H, W) with their backgrounds."""
        sources = self.inp.footage.sources
        items = [(t, [s.read(t) for s in sources] if views is None else views)
                 for t, views in items]
        H, W = self.inp.trained.frame_hw
        small = np.stack([to_model_size(views, (W, H)) for _, views in items])  # B, V, H, W, 3
        images = torch.from_numpy(small).flatten(0, 1).permute(0, 3, 1, 2).float().div_(255.0)
        return items, images, self.inp.backgrounds.repeat(len(items), 1, 1, 1)

    def hull_track(self, frames: Sequence[int]) -> ClusterTrack:
        """The hull's track to carry through the exported ``frames`` in order
        (:func:`nsd.inference.multiview.model_scene_track`: a dozen of them read first to
        decide the mixture for the scene; a video's are sought, seeking need not be
        frame-exact for a statistic)."""
        rules = self.inference.mixture
        if self.grid is None:
            return ClusterTrack(rules=rules)
        return model_scene_track(self.model, lambda t: self._read([(t, None)])[1:], frames,
                                 self.grid, rules)

    def hull_clusters(self, items: list[tuple[int, list[np.ndarray] | None]],
                      track: ClusterTrack) -> list[tuple[Tensor, Tensor]] | None:
        """The hull's individuals of the instants ``items``, with its ``track`` moved on
        through them (:func:`nsd.inference.multiview.carry_hull_track`; None without the
        hull): the parent does this for every batch in order and hands each batch its
        labels, so the hull's clustering runs through the whole export whichever worker
        decomposes a batch."""
        if self.grid is None:
            return None
        _, images, bgs = self._read(items)
        return carry_hull_track(self.model, images, bgs, len(self.names), self.grid, track)

    @torch.no_grad()
    def decompose(self, items: list[tuple[int, list[np.ndarray] | None]],
                  clusters: list[tuple[Tensor, Tensor]] | None = None,
                  mixture: bool = True) -> list[FrameResult]:
        """Decompose B instants into what :meth:`write` needs; ``items`` = [(t, native views)],
        views None: read here (footage with random access, so that workers decode too); the
        hull's individuals from ``clusters`` (:meth:`hull_clusters`; None: found here, with
        the 3D mixture tried where ``mixture``, the scene's :meth:`hull_track` decision).
        Writes no shared file (``frame_images``: each frame's own), so it may run in a
        worker."""
        items, images, bgs = self._read(items)
        if self.cfg.get("frame_images", False):
            for t, views in items:
                self._frame_images(t, views)
        V = len(self.names)
        dec = decompose_views(
            self.model,
            images,
            bgs,
            V,
            self.inference,
            self.grid,
            mask_threshold=float(self.cfg.threshold),
            refine=str(self.cfg.refine),
            clusters=clusters,
            track=ClusterTrack(mixture=mixture, rules=self.inference.mixture),
        )
        out = [self._frame(dec, b * V, t, views) for b, (t, views) in enumerate(items)]
        del dec, images, bgs
        trim_heap()
        return out

    def _frame_images(self, t: int, views: list[np.ndarray]) -> None:
        """The native frames as JPEG files, where the COCO ``file_name`` points
        (:meth:`nsd.export.inputs.ImageEntries.image_path`)."""
        for cam, view in zip(self.names, views, strict=True):
            path = self.root / ImageEntries.image_path(cam, t)
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), cv2.cvtColor(view, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise OSError(f"cannot write {path}")

    def _native_refine(self) -> bool:
        """``native_refine``: true, false, or auto (when the footage is larger than the
        training frames; at equal size the masks are the training-size ones)."""
        setting = self.cfg["native_refine"]
        if setting == "auto":
            H, W = self.inp.trained.frame_hw
            return any(s.size[0] > W or s.size[1] > H for s in self.inp.footage.sources)
        return bool(setting)

    def _frame(self, dec, first: int, t: int, views: list[np.ndarray]) -> FrameResult:
        """Instant ``t``, whose views are rows ``first ..`` of ``dec``: COCO results, appearance
        vectors and crops."""
        assoc = self._associate(dec, first)
        per_view = self._coco_results(dec, first, t, assoc, views)
        apps = [[dec.app[first + v, r["slot"]].numpy().astype(np.float32) for r in res]
                for v, res in enumerate(per_view)]
        size, margin = int(self.cfg.crop.size), float(self.cfg.crop.margin)
        thumb = int(self.cfg.views.thumbnail)
        crops = []
        for v, res in enumerate(per_view):
            crops.append([])
            for r in res:
                mask = mask_utils.decode(r["segmentation"]).astype(bool)
                window, crop, m = subject_crop(views[v], mask, r["bbox"], margin, size)
                small = cv2.resize(crop, (thumb, thumb), interpolation=cv2.INTER_AREA)
                crops[-1].append((window, crop, m, small))
        return FrameResult(t, per_view, apps, crops, self._observations(per_view, apps))

    def _write_frame(self, res: FrameResult) -> None:
        """Track and write one decomposed instant."""
        for v in range(len(self.names)):
            self.coco.add_image(self.inp.images(v, res.t))
        track = self.tracker.update(res.t, res.observations)
        pieces = self.tracker.tracklets
        rows: dict[str, list] = defaultdict(list)
        for v, cam in enumerate(self.names):
            for r, app, crop in zip(res.per_view[v], res.apps[v], res.crops[v], strict=True):
                self._write_subject(cam, res.t, r, app, crop, (track, pieces), rows)
        if rows:
            self.embeddings.write(columns(rows))

    def _associate(self, dec, first: int) -> torch.Tensor:
        """Cross-view subject ids (V, N) of one instant's windows."""
        sl = slice(first, first + len(self.names))
        slots = None if dec.slots is None else dec.slots[sl]
        one = SimpleNamespace(windows=dec.windows[sl], app=dec.app[sl], slots=slots)
        H, W = self.inp.trained.frame_hw
        bonus = self.inference.slot_bonus

        def score(v: int, r: int) -> torch.Tensor:
            return association_scores(self.model, one, self.inp.cameras, (H, W), v, r, bonus)

        return associate_views(dec.app[sl], dec.active[sl], self.dims, score)

    def _coco_results(self, dec, first: int, t: int, assoc: torch.Tensor,
                      views: list[np.ndarray]) -> list[list[dict]]:
        """Each view's COCO results at its native size, with their ``association_id``
        (``native_refine``: masks refined at native resolution, :mod:`nsd.cues.native`)."""
        per_view = []
        refine = self.native_backgrounds is not None
        for v, cam in enumerate(self.names):
            image = self.inp.images(v, t)
            native = (int(image["height"]), int(image["width"]))
            res = decomposition_to_coco(
                dec,
                first + v,
                image["id"],
                native,
                float(self.cfg.threshold),
                {"camera": cam, "frame": t},
                (views[v], self.native_backgrounds[v]) if refine else None,
                bool(self.cfg["native_colour"]),
                self.inference.speckle,
            )
            for r in res:
                r["association_id"] = int(assoc[v, r["slot"]])
            per_view.append(res)
        return per_view

    def _observations(self, per_view: list[list[dict]],
                      apps: list[list[np.ndarray]]) -> dict[int, SubjectObservation]:
        """One :class:`SubjectObservation` per association id: mean appearance, boxes and
        world position."""
        observed: dict[int, list[tuple[str, np.ndarray, np.ndarray]]] = defaultdict(list)
        for v, cam in enumerate(self.names):
            for r, app in zip(per_view[v], apps[v], strict=True):
                observed[r["association_id"]].append((cam, np.asarray(r["bbox"]), app))
        out = {}
        for aid, obs in observed.items():
            boxes = {cam: box for cam, box, _ in obs}
            out[aid] = SubjectObservation(
                unit_vectors(np.mean([unit_vectors(a[: self.dims]) for _, _, a in obs], 0)),
                boxes, point_from_views(self.inp.footage.rig,  # through the boxes' centres
                                        {c: b[:2] + b[2:] / 2 for c, b in boxes.items()})
                if self.tracker.position_weight > 0 else None)
        return out

    def _write_subject(self, cam: str, t: int, r: dict, app: np.ndarray, crop: tuple,
                       track: tuple[dict, dict], rows: dict[str, list]) -> None:
        """One subject-camera-frame: COCO annotation, crop, MOT line, sample, table row;
        ``track``: the tracker's (track ids, tracklet ids) of the frame's subjects."""
        sid, piece = (ids[r["association_id"]] for ids in track)
        ann_id = self.coco.add_annotation({**r, "subject_id": sid, "tracklet_id": piece,
                                           "iscrowd": 0})
        window, image, mask, small = crop
        self.crops.put(ann_id, sid, cam, t, window, r["bbox"], image, mask)
        self.mot.write(cam, t, sid, r["bbox"], r["score"])
        self.sample.offer(app, small, (sid, cam, t))
        x, y, w, h = r["bbox"]
        values = {
            "id": ann_id,
            "subject_id": sid,
            "tracklet_id": piece,
            "association_id": r["association_id"],
            "camera": cam,
            "frame": t,
            "image_id": r["image_id"],
            "slot": r["slot"],
            "score": r["score"],
            "depth": r["depth"],
            "bbox_x": x,
            "bbox_y": y,
            "bbox_w": w,
            "bbox_h": h,
            "area": r["area"],
            "app": app,
        }
        for k, val in values.items():
            rows[k].append(val)

    def close(self, info: dict[str, Any]) -> None:
        D = int(self.model.encoder.app_dims)
        self.coco.close(info, CATEGORIES)
        self.crops.close()
        self.mot.close()
        self.embeddings.close(columns({k: [] for k in COLUMN_TYPES}, app_dims=D))


COLUMN_TYPES = {
    "id": np.int64,
    "subject_id": np.int64,
    "tracklet_id": np.int64,
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


def columns(rows: dict[str, list], app_dims: int = 0) -> dict[str, np.ndarray]:
    """Lists of row values -> typed numpy columns (``app`` (n, D))."""
    out = {}
    for k, dtype in COLUMN_TYPES.items():
        if k == "app":
            vals = rows[k]
            out[k] = np.stack(vals).astype(np.float32) if vals else np.zeros((0, app_dims))
        else:
            out[k] = np.asarray(rows[k], dtype=dtype)
    return out
