"""Image grids of an export: a row per camera with input, boxes, visible masks, depth order."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from pycocotools import mask as mask_utils

from nsd.evaluation.visualise import decomposition_panels, grid
from nsd.io.footage import MultiViewFootage

__all__ = ["write_grids"]


def write_grids(
    export: str | Path, scene: str | Path, out: str | Path, frames: int, size: int,
    only: Sequence[int] | None = None,
) -> list[Path]:
    """One PNG per frame (``frames`` spread over the export): a row per camera with the input,
    boxes, visible masks and depth order (nearest brightest), coloured by subject id.

    Args:
        export: an ``nsd-export`` folder.
        scene: its scene folder (for the input frames).
        out: folder for ``frame_<t>.png``.
        frames: how many frames.
        size: each panel's longer side in pixels.
        only: these frames instead (e.g. the worst of a quality report).
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
    ] if only is None else np.asarray([t for t in only if t in set(all_frames)], int)
    footage = MultiViewFootage(scene)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
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
