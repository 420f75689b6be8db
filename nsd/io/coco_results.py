"""Predicted subjects as COCO results (RLE masks via pycocotools), at the footage's resolution.

One result per active window: ``image_id``, ``category_id`` (1: "subject"; NSD
is class-agnostic), ``bbox`` (tight box of the visible mask, COCO pixels),
``segmentation`` (visible mask as RLE, Fortran order, counts decoded to text),
``area``, ``score``, plus ``depth`` and ``slot`` (the window index). The same
function serves evaluation and ``nsd-export``, so COCOeval scores them alike.
"""

from __future__ import annotations

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from nsd.cues.holes import SPECKLE, Speckle
from nsd.cues.native import native_masks

__all__ = ["SUBJECT_CATEGORY", "decomposition_to_coco", "encode_rle", "resize_mask"]

SUBJECT_CATEGORY = 1


def encode_rle(mask: np.ndarray) -> dict:
    """Boolean (H, W) mask to COCO RLE with text counts."""
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    rle["counts"] = rle["counts"].decode("ascii")
    return rle


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a soft mask (H, W) to (height, width) bilinearly (identity if equal)."""
    if mask.shape == tuple(size):
        return mask
    return cv2.resize(mask.astype(np.float32), (size[1], size[0]), interpolation=cv2.INTER_LINEAR)


def decomposition_to_coco(
    dec,
    b: int,
    image_id: int,
    native_size: tuple[int, int],
    threshold: float = 0.5,
    extra: dict | None = None,
    native: tuple[np.ndarray, np.ndarray] | None = None,
    native_colour: bool = True,
    speckle: Speckle = SPECKLE,
) -> list[dict]:
    """COCO results for frame ``b`` of an :class:`nsd.inference.single.Decomposition`.

    Args:
        dec: the decomposition.
        b: index of the frame (view) in the batch.
        image_id: COCO image id of this camera-frame.
        native_size: (H, W) of the footage (masks are upsampled to it).
        threshold: visible-mask threshold.
        extra: fields added to every result (e.g. camera, frame).
        native: (frame, background), native uint8 RGB: the masks are refined at native
            resolution (:func:`nsd.cues.native.native_masks`) instead of upsampled
            and thresholded.
        native_colour: at native resolution, the subjects' colours move the boundaries
            between them (:func:`nsd.cues.native.colour_owners`).
        speckle: at native resolution, the masks' speckle cleaned
            (:class:`nsd.cues.holes.Speckle`).
    """
    out = []
    active = np.flatnonzero(dec.active[b].cpu().numpy())
    refined = None
    if native is not None and len(active):
        low = (dec.masks[b, active].cpu().numpy() > threshold).astype(np.float32)
        refined = native_masks(low, *native, colour=native_colour, speckle=speckle)
    for j, k in enumerate(active):
        if refined is not None:
            m = refined[j]
        else:
            m = resize_mask(dec.masks[b, k].cpu().numpy(), native_size) > threshold
        if not m.any():
            continue
        rle = encode_rle(m)
        out.append(
            {
                "image_id": int(image_id),
                "category_id": SUBJECT_CATEGORY,
                "bbox": [float(v) for v in mask_utils.toBbox(rle)],
                "segmentation": rle,
                "area": float(m.sum()),
                "score": float(dec.scores[b, k]),
                "depth": float(dec.depths[b, k]),
                "slot": int(k),
                **(extra or {}),
            }
        )
    return out
