"""Ground truth of a synthetic scene in the shape the evaluation needs.

Wraps :class:`nsd.synth.groundtruth.SyntheticScene`: per camera-frame the
visible and amodal masks, visible boxes and identities of the individuals that
are at least partly visible, optionally resized to the evaluation resolution
(nearest neighbour for masks, scaled boxes), and the COCO image id.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from nsd.core.errors import ConfigError
from nsd.synth.groundtruth import SyntheticScene

__all__ = ["FrameGT", "GroundTruth"]


@dataclass
class FrameGT:
    """Visible individuals of one camera-frame.

    Attributes:
        visible, amodal: (G, H, W) bool at the requested size.
        boxes: visible boxes (G, 4), COCO pixels at the requested size.
        identity: (G,) identity ids.
        image_id: COCO image id.
        native_size: (H, W) of the footage.
    """

    visible: np.ndarray
    amodal: np.ndarray
    boxes: np.ndarray
    identity: np.ndarray
    image_id: int
    native_size: tuple[int, int]


def _resize_masks(masks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if masks.shape[-2:] == tuple(size) or len(masks) == 0:
        return masks.reshape(len(masks), *size) if len(masks) == 0 else masks
    return np.stack(
        [
            cv2.resize(m.astype(np.uint8), (size[1], size[0]), interpolation=cv2.INTER_NEAREST) > 0
            for m in masks
        ]
    )


def _tight_boxes(masks: np.ndarray) -> np.ndarray:
    out = np.zeros((len(masks), 4))
    for k, m in enumerate(masks):
        ys, xs = np.nonzero(m)
        if len(xs):
            out[k] = [xs.min(), ys.min(), xs.max() + 1 - xs.min(), ys.max() + 1 - ys.min()]
    return out


class GroundTruth:
    """Evaluation view of a synthetic scene's ``gt/`` folder."""

    def __init__(self, scene: str | os.PathLike) -> None:
        self.scene = SyntheticScene(scene)
        self.root = Path(scene)

    @staticmethod
    def exists(scene: str | os.PathLike) -> bool:
        """The scene has ground truth that masks can be scored against: ``gt/scene.json`` and
        the per camera-frame maps ``gt/dense/`` (a scene written with ``dense=false`` has
        keypoints and boxes but no masks)."""
        gt = Path(scene) / "gt"
        return (gt / "scene.json").is_file() and any((gt / "dense").glob("*/000000.npz"))

    @classmethod
    def load(cls, scene: str | os.PathLike) -> GroundTruth:
        return cls(scene)

    @cached_property
    def coco(self):
        return self.scene.coco()

    @cached_property
    def _image_ids(self) -> dict[tuple[str, int], int]:
        return {
            (im["camera"], int(im["frame"])): int(im["id"]) for im in self.coco.dataset["images"]
        }

    def image_id(self, camera: str, frame: int) -> int:
        return self._image_ids[(camera, int(frame))]

    def frame(self, camera: str, frame: int, size: tuple[int, int] | None = None) -> FrameGT:
        """Individuals visible in one camera-frame, at ``size`` = (H, W) (default native)."""
        d = self.scene.dense(camera, frame, ("instance", "amodal"))
        inst, amodal = d["instance"], d["amodal"]
        native = inst.shape
        ids = np.flatnonzero(np.bincount(inst[inst >= 0].ravel()))  # (a hash unique: 10x slower)
        visible = np.stack([inst == i for i in ids]) if len(ids) else np.zeros((0, *native), bool)
        amo = amodal[ids] if len(ids) else np.zeros((0, *native), bool)
        size = tuple(size) if size is not None else native
        visible, amo = _resize_masks(visible, size), _resize_masks(amo, size)
        keep = visible.reshape(len(ids), -1).any(1) if len(ids) else np.zeros(0, bool)
        visible, amo, ids = visible[keep], amo[keep], ids[keep]
        return FrameGT(
            visible, amo, _tight_boxes(visible), ids, self.image_id(camera, frame), native
        )

    @property
    def num_keypoints(self) -> int:
        counts = {v.shape[1] for v in self.scene.keypoints3d.values()}
        if len(counts) != 1:
            raise ConfigError("the pose stage needs individuals of one species (one K)")
        return counts.pop()

    def keypoints3d(self, frame: int) -> dict[int, np.ndarray]:
        """Identity -> world keypoints (K, 3) at ``frame``."""
        return {i: kp[frame] for i, kp in self.scene.keypoints3d.items()}
