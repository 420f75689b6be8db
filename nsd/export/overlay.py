"""Overlay videos of an export: every camera's footage with the subjects drawn on it.

One video per camera, ``<out>/<camera>.mp4``: each subject's visible mask (tinted by its
identity, or its track where there are no identities), its box, a label ``id <n>`` with
its depth rank among the camera's subjects (``d1`` nearest), drawn far to near, and a
frame counter. H.264 (``avc1``) where the OpenCV build can write it, else MPEG-4 Part 2
(``mp4v``); frames are scaled so that the longer side is ``size`` pixels.
"""

from __future__ import annotations

import functools
import json
import os
import tempfile
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from nsd.evaluation.visualise import PALETTE
from nsd.io.footage import MultiViewFootage

__all__ = ["CODECS", "draw_subjects", "write_overlay_videos"]

CODECS = ("avc1", "mp4v")  # tried in this order
ALPHA = 0.45  # mask tint


@functools.cache
def _codec() -> str:
    """The first of :data:`CODECS` this OpenCV build writes; probed once, with the native
    library's complaints about the codecs it lacks kept off the user's screen."""
    with tempfile.TemporaryDirectory() as tmp, open(os.devnull, "w") as null:
        saved = os.dup(2)
        os.dup2(null.fileno(), 2)
        try:
            for codec in CODECS:
                w = cv2.VideoWriter(str(Path(tmp) / "probe.mp4"),
                                    cv2.VideoWriter_fourcc(*codec), 25.0, (64, 48))
                ok = w.isOpened()
                w.release()
                if ok:
                    return codec
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    raise OSError(f"this OpenCV build writes none of the video codecs {CODECS}")


def _writer(path: Path, fps: float, size: tuple[int, int]) -> tuple[cv2.VideoWriter, str]:
    codec = _codec()
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, size)
    if not w.isOpened():
        raise OSError(f"OpenCV cannot write {path} ({codec})")
    return w, codec


def draw_subjects(img: np.ndarray, anns: list[dict], ids: list[int], scale: float,
                  frame: int) -> np.ndarray:
    """One frame (RGB, already scaled by ``scale``) with the subjects drawn far to near.

    Args:
        img: RGB uint8 (H, W, 3) at the output size.
        anns: the frame's export annotations (``segmentation``, ``bbox``, ``depth``; footage
            pixels).
        ids: the id drawn for each annotation (colour and label).
        scale: output pixels per footage pixel.
        frame: the footage frame index (the counter).
    """
    out = img.copy()
    h, w = out.shape[:2]
    order = np.argsort([-float(a.get("depth", 0.0)) for a in anns])  # far first
    rank = {int(k): r + 1 for r, k in enumerate(order[::-1])}  # 1: nearest
    for k in order:
        a, colour = anns[k], tuple(int(c) for c in PALETTE[ids[k] % len(PALETTE)])
        m = mask_utils.decode(a["segmentation"]).astype(np.uint8)
        m = cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
        out[m] = (out[m] * (1 - ALPHA) + np.asarray(colour) * ALPHA).astype(np.uint8)
        x, y, bw, bh = (v * scale for v in a["bbox"])
        cv2.rectangle(out, (round(x), round(y)), (round(x + bw), round(y + bh)), colour, 2)
        cv2.putText(out, f"id {ids[k]} d{rank[int(k)]}", (round(x), max(12, round(y) - 4)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    cv2.putText(out, f"frame {frame}", (6, h - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _id(ann: dict, row_ids: dict[int, int] | None) -> int:
    """The row's identity, or its track where it has none."""
    ident = row_ids.get(int(ann["id"]), -1) if row_ids else -1
    return ident if ident >= 0 else int(ann["subject_id"])


def write_overlay_videos(export: str | Path, scene: str | Path, out: str | Path,
                         row_ids: dict[int, int] | None = None, size: int = 480,
                         fps: float = 25.0) -> dict[str, object]:
    """Write ``<out>/<camera>.mp4`` for every camera of an export.

    Args:
        export: nsd-export folder (``subjects.coco.json``).
        scene: its scene folder (the footage).
        out: folder for the videos (created).
        row_ids: annotation id -> identity (drawn and coloured); rows without one, or
            without ``row_ids``, show their track (``subject_id``).
        size: the longer side of the videos in pixels (even sizes are kept even).
        fps: frames per second of the videos.

    Returns:
        ``{"codec": ..., "frames": {camera: n}}``.
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    anns_by_image: dict[int, list[dict]] = defaultdict(list)
    for a in coco["annotations"]:
        anns_by_image[int(a["image_id"])].append(a)
    images = {(im["camera"], int(im["frame"])): int(im["id"]) for im in coco["images"]}
    footage = MultiViewFootage(scene)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written, codec = {}, ""
    for v, cam in enumerate(footage.camera_names):
        frames = sorted(t for c, t in images if c == cam)
        if not frames:
            continue
        src = footage.sources[v]
        w0, h0 = src.size
        s = size / max(w0, h0)
        ow, oh = 2 * round(w0 * s / 2), 2 * round(h0 * s / 2)
        writer, codec = _writer(out / f"{cam}.mp4", fps, (ow, oh))
        wanted = set(frames)
        try:
            for t, img in zip(range(frames[0], frames[-1] + 1),
                              src.iter_range(frames[0], frames[-1] + 1), strict=True):
                if t not in wanted:
                    continue
                anns = anns_by_image.get(images[(cam, t)], [])
                ids = [_id(a, row_ids) for a in anns]
                small = cv2.resize(img, (ow, oh), interpolation=cv2.INTER_AREA)
                drawn = draw_subjects(small, anns, ids, ow / w0, t)
                writer.write(cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
        finally:
            writer.release()
        written[cam] = len(frames)
    return {"codec": codec, "frames": written}
