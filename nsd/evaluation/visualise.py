"""Image grids a person can look at: inputs, re-synthesised views, boxes, masks, depth order."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from nsd.core.device import call_on_device
from nsd.inference.single import decompose

__all__ = [
    "PALETTE",
    "decomposition_panels",
    "draw_boxes",
    "grid",
    "instance_overlay",
    "training_grid",
]

PALETTE = np.array(
    [
        [230, 25, 75],
        [60, 180, 75],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
        [250, 190, 190],
        [0, 128, 128],
    ],
    dtype=np.uint8,
)


def to_uint8(img: Tensor | np.ndarray) -> np.ndarray:
    """(3, H, W) float [0, 1] tensor or (H, W, 3) array -> (H, W, 3) uint8."""
    if isinstance(img, Tensor):
        img = img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy()
        return (img * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(img, dtype=np.uint8)


def draw_boxes(
    img: np.ndarray,
    boxes: np.ndarray,
    ids: Sequence[int] | None = None,
    labels: Sequence[str] | None = None,
) -> np.ndarray:
    """Draw COCO boxes [x, y, w, h] (pixels) in palette colours; returns a copy."""
    out = img.copy()
    for k, (x, y, w, h) in enumerate(np.asarray(boxes, dtype=float)):
        if w <= 0 or h <= 0:
            continue
        c = tuple(int(v) for v in PALETTE[(ids[k] if ids is not None else k) % len(PALETTE)])
        cv2.rectangle(out, (int(x), int(y)), (int(x + w) - 1, int(y + h) - 1), c, 1)
        if labels is not None:
            cv2.putText(out, labels[k], (int(x) + 1, int(y) + 8), cv2.FONT_HERSHEY_PLAIN, 0.6, c, 1)
    return out


def instance_overlay(
    img: np.ndarray, masks: np.ndarray, ids: Sequence[int] | None = None, alpha: float = 0.55
) -> np.ndarray:
    """Colour soft or boolean instance masks (N, H, W) over an image."""
    out = img.astype(np.float32)
    for k, m in enumerate(np.asarray(masks, dtype=np.float32)):
        c = PALETTE[(ids[k] if ids is not None else k) % len(PALETTE)].astype(np.float32)
        a = (alpha * m)[..., None]
        out = out * (1 - a) + c * a
    return out.clip(0, 255).astype(np.uint8)


def depth_order_image(masks: np.ndarray, depths: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Visible subjects shaded by depth rank (nearest brightest), black background."""
    H, W = masks.shape[-2:]
    out = np.zeros((H, W, 3), np.uint8)
    order = np.argsort(depths)  # nearest first
    n = max(1, len(order))
    for rank, k in enumerate(order[::-1]):  # paint far to near
        shade = int(255 * (1 - 0.7 * (n - 1 - rank) / max(1, n - 1))) if n > 1 else 255
        out[masks[k] > threshold] = (
            np.array(PALETTE[k % len(PALETTE)], float) * shade / 255
        ).astype(np.uint8)
    return out


def grid(rows: Sequence[Sequence[np.ndarray]], pad: int = 2, scale: int = 1) -> np.ndarray:
    """Tile (H, W, 3) images into one image (rows x columns); each cell is as large as the
    largest image, and a smaller one (a camera of another size) sits at its top left."""
    H = max(im.shape[0] for r in rows for im in r)
    W = max(im.shape[1] for r in rows for im in r)
    ncol = max(len(r) for r in rows)
    out = np.full((len(rows) * (H + pad) + pad, ncol * (W + pad) + pad, 3), 255, np.uint8)
    for i, r in enumerate(rows):
        for j, im in enumerate(r):
            y, x = pad + i * (H + pad), pad + j * (W + pad)
            out[y : y + im.shape[0], x : x + im.shape[1]] = im
    if scale > 1:
        out = cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    return out


def decomposition_panels(
    image: np.ndarray, dec, b: int, ids: Sequence[int] | None = None
) -> list[np.ndarray]:
    """Panels of one frame of a :class:`nsd.inference.single.Decomposition`: boxes, masks, depth."""
    act = dec.active[b].cpu().numpy()
    masks = dec.masks[b].cpu().numpy()
    boxes = dec.boxes[b].cpu().numpy()
    depths = dec.depths[b].cpu().numpy()
    sel = np.flatnonzero(act)
    idl = [ids[k] for k in sel] if ids is not None else list(sel)
    labels = [f"{i}:z{depths[k]:.1f}" for i, k in zip(idl, sel, strict=True)]
    return [
        draw_boxes(image, boxes[sel], idl, labels),
        instance_overlay(image, masks[sel], idl),
        depth_order_image(masks[sel], depths[sel]),
    ]


@torch.no_grad()
def training_grid(model, data, frames: Sequence[int]) -> np.ndarray:
    """Per frame and per view pair (0, 1): input v, re-synthesis of v from w, boxes,
    instance masks, depth order, and the own-view reconstruction."""

    was = model.training
    model.eval()
    rows = []
    try:
        for t in frames:
            views, bgs = data.views(int(t))
            v, w = 0, 1 % data.num_views
            rv, _, _, _ = call_on_device(
                model,
                model,
                views[v : v + 1],
                views[w : w + 1],
                bgs[v : v + 1],
                bgs[w : w + 1],
                data.rotations[v, w][None],
            )
            dec = decompose(model, views[v : v + 1], bgs[v : v + 1])
            img = to_uint8(views[v])
            rows.append(
                [
                    img,
                    to_uint8(rv.image[0]),
                    *decomposition_panels(img, dec, 0),
                    to_uint8(dec.reconstruction[0]),
                ]
            )
    finally:
        model.train(was)
    return grid(rows, scale=2)
