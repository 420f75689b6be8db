"""The writers of one export folder and the per-batch work (:class:`SubjectWriter`).

Each batch of instants is decomposed (:func:`nsd.inference.multiview.decompose_views`), its
windows get cross-view subject ids and track ids, and every subject-camera-frame is written
as it is produced: a COCO annotation, a crop, a MOT line, a sampled vector and a table row
(:data:`COLUMN_TYPES`; ``datasets/export.md`` lists every column).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig
from pycocotools import mask as mask_utils

from nsd.core.memory import trim_heap
from nsd.cues.occupancy import working_volume
from nsd.export.inputs import ExportInputs, ImageEntries, to_model_size
from nsd.export.positions import point_from_views
from nsd.inference.association_scores import association_scores
from nsd.inference.multiview import InferenceSettings, decompose_views
from nsd.inference.single import associate_views
from nsd.inference.tracking import SubjectObservation, SubjectTracker
from nsd.io.coco import CocoStreamWriter
from nsd.io.coco_results import SUBJECT_CATEGORY, decomposition_to_coco
from nsd.io.crops import CropWriter
from nsd.io.embedding_views import Reservoir
from nsd.io.embeddings import EmbeddingWriter
from nsd.io.mot import MotWriter
from nsd.ops.vectors import unit_vectors

__all__ = ["CATEGORIES", "COLUMN_TYPES", "SubjectWriter", "columns"]


JPEG_QUALITY = 95  # frame_images: the exported frames as JPEG of this quality
CATEGORIES = [{"id": SUBJECT_CATEGORY, "name": "subject", "supercategory": "subject"}]


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
            float(t.position_weight), self._position_scale(t.position_scale),
        )
        self.grid = (
            self.inference.grid(inp.footage.rig, inp.trained.frame_hw)
            if self.inference.multiview
            else None
        )
        self.frames_done = 0
        self.native_backgrounds: list[np.ndarray] | None = None  # native_refine, on first use

    def batch(self, items: list[tuple[int, list[np.ndarray]]]) -> None:
        """Decompose and write B instants: ``items`` = [(t, native views)]."""
        V = len(self.names)
        H, W = self.inp.trained.frame_hw
        small = np.stack([to_model_size(views, (W, H)) for _, views in items])  # B, V, H, W, 3
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
            if self.cfg.get("frame_images", False):
                self._frame_images(t, views)
        self.frames_done += len(items)
        del dec, images, bgs, small
        trim_heap()

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

    def _frame(self, dec, first: int, t: int, views: list[np.ndarray]) -> None:
        """Write instant ``t``, whose views are rows ``first ..`` of ``dec``."""
        assoc = self._associate(dec, first)
        per_view = self._coco_results(dec, first, t, assoc, views)
        track = self.tracker.update(t, self._observations(dec, first, per_view))
        rows: dict[str, list] = defaultdict(list)
        for v, cam in enumerate(self.names):
            for r in per_view[v]:
                self._write_subject(dec, first + v, cam, t, views[v], r, track, rows)
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
        refine = self._native_refine()
        if refine and self.native_backgrounds is None:
            self.native_backgrounds = [self.inp.footage.native_background(v)
                                       for v in range(len(self.names))]
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
                (views[v], self.native_backgrounds[v]) if refine else None,
                bool(self.cfg["native_colour"]),
            )
            for r in res:
                r["association_id"] = int(assoc[v, r["slot"]])
            per_view.append(res)
        return per_view

    def _position_scale(self, setting) -> float:
        """``tracking.position_scale``: a distance in metres, or ``auto`` (two sides of a
        voxel of the hull's grid: a fraction of the working volume, whatever the scene's
        size)."""
        if setting == "auto":
            _, half, _ = working_volume(self.inp.footage.rig)
            return 2 * (2 * half / int(self.inference.resolution))
        return float(setting)

    def _observations(self, dec, first: int, per_view: list[list[dict]]) -> dict:
        """One :class:`SubjectObservation` per association id: mean appearance, boxes and
        world position."""
        observed: dict[int, list[tuple[str, np.ndarray, np.ndarray]]] = defaultdict(list)
        for v, cam in enumerate(self.names):
            for r in per_view[v]:
                app = dec.app[first + v, r["slot"]].numpy()
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

    def _write_subject(
        self,
        dec,
        row: int,
        cam: str,
        t: int,
        view: np.ndarray,
        r: dict,
        track: dict,
        rows: dict[str, list],
    ) -> None:
        """One subject-camera-frame: COCO annotation, crop, MOT line, sample, table row."""
        sid = track[r["association_id"]]
        ann_id = self.coco.add_annotation({**r, "subject_id": sid, "iscrowd": 0})
        mask = mask_utils.decode(r["segmentation"]).astype(bool)
        crop, _ = self.crops.add(
            ann_id, sid, cam, t, view, mask, r["bbox"], float(self.cfg.crop.margin)
        )
        self.mot.write(cam, t, sid, r["bbox"], r["score"])
        app = dec.app[row, r["slot"]].numpy().astype(np.float32)
        thumb = int(self.cfg.views.thumbnail)
        small = cv2.resize(crop, (thumb, thumb), interpolation=cv2.INTER_AREA)
        self.sample.offer(app, small, (sid, cam, t))
        x, y, w, h = r["bbox"]
        values = {
            "id": ann_id,
            "subject_id": sid,
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
