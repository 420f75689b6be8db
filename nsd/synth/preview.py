"""Image grids of a scene for people to look at (``gt/preview.png``).

Rows are cameras, columns frames. Each cell shows two panels side by side:

* the image with every individual's visible mask tinted in its colour, its
  amodal outline drawn in the same colour, and its keypoints (filled dots:
  visible, ``v = 2``; hollow: occluded, ``v = 1``);
* the NNOPCS map (x, y, z as R, G, B) over the darkened image.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["INSTANCE_COLOURS", "preview_cell", "preview_grid"]

INSTANCE_COLOURS = np.array(
    [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48),
     (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60)],
    dtype=np.uint8,
)  # fmt: skip
MASK_ALPHA = 0.45
GAP = 2  # pixels between panels and cells


def _outline(mask: np.ndarray) -> np.ndarray:
    m = mask.astype(np.uint8)
    return (m - cv2.erode(m, np.ones((3, 3), np.uint8))).astype(bool)


def preview_cell(
    rgb: np.ndarray,
    instance: np.ndarray,
    amodal: np.ndarray,
    nnopcs: np.ndarray,
    keypoints: Sequence[np.ndarray] = (),
    label: str = "",
    zoom: int = 2,
) -> np.ndarray:
    """One cell: overlay panel and NNOPCS panel side by side.

    Args:
        rgb: image, uint8 (H, W, 3).
        instance: (H, W) int, -1 on background.
        amodal: (N, H, W) bool.
        nnopcs: (H, W, 3) float in [0, 1].
        keypoints: per individual (K, 3): pixel x, y and visibility.
        label: text written in the top-left corner.
        zoom: integer upscaling.

    Returns:
        uint8 (H * zoom, 2 * W * zoom + GAP, 3).
    """
    up = lambda x: np.repeat(np.repeat(x, zoom, axis=0), zoom, axis=1)  # noqa: E731
    img = up(rgb).astype(np.float32)
    inst = up(instance)
    over = img.copy()
    for n in range(amodal.shape[0]):
        c = INSTANCE_COLOURS[n % len(INSTANCE_COLOURS)].astype(np.float32)
        m = inst == n
        over[m] = (1 - MASK_ALPHA) * over[m] + MASK_ALPHA * c
        over[_outline(up(amodal[n]))] = c
    over = np.ascontiguousarray(over.clip(0, 255).astype(np.uint8))
    for n, kp in enumerate(keypoints):
        c = tuple(int(v) for v in INSTANCE_COLOURS[n % len(INSTANCE_COLOURS)])
        for x, y, v in np.asarray(kp):
            if v > 0:
                centre = (round((x + 0.5) * zoom - 0.5), round((y + 0.5) * zoom - 0.5))
                cv2.circle(over, centre, max(1, zoom), c, -1 if v == 2 else 1, cv2.LINE_AA)
    fg = up(instance >= 0)[..., None]
    nn = np.where(fg, up(nnopcs) * 255.0, img * 0.3).clip(0, 255).astype(np.uint8)
    cell = np.concatenate([over, np.full((over.shape[0], GAP, 3), 255, np.uint8), nn], axis=1)
    if label:
        cv2.putText(
            cell, label, (3, 11), cv2.FONT_HERSHEY_PLAIN, 0.8, (255, 255, 255), 1, cv2.LINE_AA
        )
    return cell


def preview_grid(cells: Sequence[Sequence[np.ndarray]]) -> np.ndarray:
    """Stack cells (rows of equal-sized uint8 images) into one grid with white gaps."""
    rows = []
    for row in cells:
        parts = []
        for c in row:
            parts += [c, np.full((c.shape[0], GAP, 3), 255, np.uint8)]
        rows.append(np.concatenate(parts[:-1], axis=1))
    width = max(r.shape[1] for r in rows)
    out = []
    for r in rows:
        r = np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255)
        out += [r, np.full((GAP, width, 3), 255, np.uint8)]
    return np.concatenate(out[:-1], axis=0)
