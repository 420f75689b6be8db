"""What an export reads: the trained decomposition, the scene's footage, frames and COCO images.

:func:`prepare_inputs` checks the checkpoint against the scene's cameras before any frame
is decoded; :class:`ImageEntries` gives every camera-frame its COCO image entry (the
ground truth's when the scene has one, so that ``COCOeval`` scores the export directly).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from nsd.cameras.batch import CameraBatch
from nsd.cameras.calibration_io import read_calibration
from nsd.core.device import resolve_device
from nsd.core.errors import FootageError
from nsd.io.footage import MultiViewFootage
from nsd.io.frame_selection import select_frames
from nsd.io.frame_sources import ImageFolderSource
from nsd.io.scenes import resolve_scene
from nsd.model.checkpoint import TrainedDecomposition, load_decomposition

__all__ = ["ExportInputs", "ImageEntries", "prepare_inputs", "to_model_size"]


@dataclass
class ExportInputs:
    """The scene as the export sees it."""

    trained: TrainedDecomposition
    footage: MultiViewFootage  # at the training size: rig, backgrounds; sources are native
    scene: Path
    frames: np.ndarray
    images: ImageEntries  # (view, frame) -> COCO image entry
    backgrounds: torch.Tensor  # (V, 3, H, W) in [0, 1]
    cameras: CameraBatch  # stacked K, R, t, dist at the training size


class ImageEntries:
    """COCO image entries of camera-frames (see the module docstring for the ids).

    With ground truth, its image table (the selected entries) is kept; otherwise
    entries are computed when asked, so nothing here grows with the footage.
    """

    def __init__(self, footage: MultiViewFootage, scene: Path, frames: np.ndarray,
                 frame_images: bool = False) -> None:
        self.footage, self.scene, self.frame_images = footage, scene, frame_images
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
        names = footage.calibration_names
        self.index = {c: names.index(c) for c in footage.camera_names}
        self.num_cameras = len(names)

    @staticmethod
    def image_path(camera: str, t: int) -> str:
        """Where ``frame_images`` puts a camera-frame, relative to the export folder."""
        return f"images/{camera}/{t:06d}.jpg"

    def __call__(self, v: int, t: int) -> dict:
        cam = self.footage.camera_names[v]
        if self.gt is not None:
            entry = self.gt[(cam, t)]
            return dict(entry, file_name=self.image_path(cam, t)) if self.frame_images else entry
        src = self.footage.sources[v]
        if self.frame_images:
            name = self.image_path(cam, t)
        elif isinstance(src, ImageFolderSource):
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


def prepare_inputs(cfg: DictConfig) -> ExportInputs:
    trained = load_decomposition(cfg.checkpoint, resolve_device(cfg.device))
    scene = cfg.scene or trained.config.data.get("scene")
    if not scene:
        scene = resolve_scene(None)
    scene = Path(scene).expanduser()
    H, W = trained.frame_hw
    cameras = list(cfg.cameras) if cfg.cameras is not None else None
    units = trained.config.data.get("units", "auto")  # the unit the model was trained with
    calibration = read_calibration(scene, units) if scene.is_dir() else None  # read once
    if cameras is None and calibration is not None:
        trained.check_cameras(calibration.names, scene)
    footage = MultiViewFootage(  # the background as trained (checkpoints before it: median)
        scene, cameras=cameras, image_size=(W, H), calibration=calibration,
        background=trained.config.data.get("background", "median"))
    trained.check_cameras(footage.camera_names, scene)
    frames = select_frames(
        OmegaConf.to_object(cfg.frames) if OmegaConf.is_config(cfg.frames) else cfg.frames,
        footage.num_frames,
    )
    bg = torch.from_numpy(footage.background()).permute(0, 3, 1, 2).float().div_(255.0)
    return ExportInputs(
        trained,
        footage,
        scene,
        frames,
        ImageEntries(footage, scene, frames, bool(cfg.get("frame_images", False))),
        bg,
        footage.rig.stacked(torch.float32),
    )


def to_model_size(views: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """Resize native views to the training size (W, H) as MultiViewFootage does: (V, H, W, 3)."""
    return np.stack(
        [
            v
            if (v.shape[1], v.shape[0]) == size
            else cv2.resize(v, size, interpolation=cv2.INTER_AREA)
            for v in views
        ]
    )
