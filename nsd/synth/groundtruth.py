"""The ``gt/`` folder of a synthetic scene: dense-map files and a reader for all of it.

Dense maps, one compressed ``.npz`` per camera-frame (``gt/dense/<cam>/<frame:06d>.npz``)
    ``depth`` float32 (H, W): camera-space Z in metres of the visible
    individual, ``inf`` on background; ``instance`` int8 (H, W): individual
    index (= identity id), -1 on background; ``part`` int8 (H, W): primitive
    index within the species (``scene.json`` lists them), -1 on background;
    ``nnopcs`` uint16 (H, W, 3): NNOPCS times 65535, 0 on background;
    ``amodal`` uint8 (N, H, ceil(W / 8)): amodal masks packed along the width
    with :func:`numpy.packbits`; ``amodal_shape`` int32 (3,): (N, H, W).

Static backdrop, per camera
    ``gt/background/<cam>.png``: the backdrop alone (RGB, the exact median
    background); ``gt/dense/<cam>/background.npz``: ``depth`` float32 (H, W)
    camera-space Z of the ground or wall, ``inf`` on the sky.

:func:`load_dense` undoes the packing; :class:`SyntheticScene` reads the whole
``gt/`` folder (see ``datasets/synthetic.md``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
from pycocotools.coco import COCO

from nsd.core.errors import FootageError

__all__ = ["NNOPCS_SCALE", "SyntheticScene", "load_dense", "save_dense"]

NNOPCS_SCALE = 65535.0  # uint16 code of NNOPCS value 1.0


def save_dense(
    path: str | os.PathLike,
    depth: np.ndarray,
    instance: np.ndarray,
    part: np.ndarray,
    nnopcs: np.ndarray,
    amodal: np.ndarray,
) -> None:
    """Write one camera-frame's dense maps (see the module docstring for dtypes)."""
    np.savez_compressed(
        path,
        depth=depth.astype(np.float32),
        instance=instance.astype(np.int8),
        part=part.astype(np.int8),
        nnopcs=np.round(np.clip(nnopcs, 0, 1) * NNOPCS_SCALE).astype(np.uint16),
        amodal=np.packbits(amodal.astype(bool), axis=-1),
        amodal_shape=np.asarray(amodal.shape, dtype=np.int32),
    )


DENSE_KEYS = ("depth", "instance", "part", "nnopcs", "amodal")


def load_dense(path: str | os.PathLike,
               keys: Sequence[str] = DENSE_KEYS) -> dict[str, np.ndarray]:
    """Read one camera-frame's dense maps (only ``keys``: each is decompressed when read,
    which at HD sizes is most of the cost).

    Returns:
        ``depth`` float32 (H, W), ``instance`` int64 (H, W), ``part`` int64 (H, W),
        ``nnopcs`` float32 (H, W, 3) in [0, 1], ``amodal`` bool (N, H, W), as asked.
    """
    read = {
        "depth": lambda z: z["depth"],
        "instance": lambda z: z["instance"].astype(np.int64),
        "part": lambda z: z["part"].astype(np.int64),
        "nnopcs": lambda z: z["nnopcs"].astype(np.float32) / NNOPCS_SCALE,
        "amodal": lambda z: np.unpackbits(
            z["amodal"], axis=-1, count=int(z["amodal_shape"][2])).astype(bool),
    }
    with np.load(path) as z:
        return {k: read[k](z) for k in keys}


class SyntheticScene:
    """Read the ground truth of a scene written by :func:`nsd.synth.scene.write_scene`.

    Args:
        scene: the scene folder.
    """

    def __init__(self, scene: str | os.PathLike) -> None:
        self.root = Path(scene)
        meta = self.root / "gt" / "scene.json"
        if not meta.is_file():
            raise FootageError(f"{self.root}: no gt/scene.json; not a synthetic scene")
        self.meta = json.loads(meta.read_text())

    @property
    def camera_names(self) -> list[str]:
        return [c["name"] for c in self.meta["cameras"]]

    @property
    def num_frames(self) -> int:
        return int(self.meta["num_frames"])

    @property
    def individuals(self) -> list[dict]:
        return self.meta["individuals"]

    def _camera(self, camera: str | int) -> str:
        return self.camera_names[camera] if isinstance(camera, int) else camera

    def dense(self, camera: str | int, frame: int,
              keys: Sequence[str] = DENSE_KEYS) -> dict[str, np.ndarray]:
        """Dense maps of one camera-frame (:func:`load_dense`)."""
        return load_dense(self.root / "gt" / "dense" / self._camera(camera) / f"{frame:06d}.npz",
                          keys)

    def background(self, camera: str | int) -> tuple[np.ndarray, np.ndarray]:
        """The backdrop of a camera: RGB uint8 (H, W, 3) and camera-space Z (H, W)."""
        cam = self._camera(camera)
        img = cv2.cvtColor(
            cv2.imread(str(self.root / "gt" / "background" / f"{cam}.png")), cv2.COLOR_BGR2RGB
        )
        with np.load(self.root / "gt" / "dense" / cam / "background.npz") as z:
            return img, z["depth"]

    @cached_property
    def keypoints3d(self) -> dict[int, np.ndarray]:
        """Identity id -> world keypoints (T, K, 3) float64, metres."""
        with np.load(self.root / "gt" / "keypoints3d.npz") as z:
            return {int(k.split("_")[1]): z[k] for k in z.files}

    @cached_property
    def keypoints2d(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Identity id -> (pixels (T, V, K, 2) float64, visibility (T, V, K) uint8)."""
        with np.load(self.root / "gt" / "keypoints2d.npz") as z:
            ids = sorted({int(k.split("_")[1]) for k in z.files})
            return {i: (z[f"identity_{i}_uv"], z[f"identity_{i}_visibility"]) for i in ids}

    @cached_property
    def poses(self) -> dict[int, dict[str, np.ndarray]]:
        """Identity id -> ``translation`` (T, 3), ``heading`` (T,), ``angles`` (T, K, 3)."""
        out: dict[int, dict[str, np.ndarray]] = {}
        with np.load(self.root / "gt" / "poses.npz") as z:
            for k in z.files:
                _, i, name = k.split("_", 2)
                out.setdefault(int(i), {})[name] = z[k]
        return out

    def coco(self):
        """The COCO ground truth as a :class:`pycocotools.coco.COCO`."""

        coco = COCO()
        coco.dataset = json.loads((self.root / "gt" / "coco.json").read_text())
        coco.createIndex()
        return coco
