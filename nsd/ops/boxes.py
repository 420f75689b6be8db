"""Boxes and masks: tight boxes of masks, IoU matrices and their Hungarian matching.

One box convention per name: ``xyxy`` is ``[x0, y0, x1, y1]`` and ``xywh`` is COCO's
``[x, y, w, h]``, both in pixel-edge coordinates (pixel ``i`` spans ``[i, i + 1)``).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

__all__ = [
    "box_iou_xywh",
    "mask_boxes_xywh",
    "mask_boxes_xyxy",
    "mask_iou",
    "match",
    "xyxy_to_xywh",
]


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """IoU matrix of boolean masks pred (P, H, W) and gt (G, H, W): (P, G)."""
    p = pred.reshape(len(pred), -1).astype(np.float32)
    g = gt.reshape(len(gt), -1).astype(np.float32)
    inter = p @ g.T
    union = p.sum(1)[:, None] + g.sum(1)[None] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-9), 0.0)


def box_iou_xywh(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix of COCO boxes [x, y, w, h]: a (P, 4), b (G, 4) -> (P, G)."""
    a, b = np.asarray(a, float).reshape(-1, 4), np.asarray(b, float).reshape(-1, 4)
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 0] + a[:, None, 2], b[None, :, 0] + b[None, :, 2])
    y1 = np.minimum(a[:, None, 1] + a[:, None, 3], b[None, :, 1] + b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    union = (a[:, 2] * a[:, 3])[:, None] + (b[:, 2] * b[:, 3])[None] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-9), 0.0)


def match(iou: np.ndarray) -> list[tuple[int, int]]:
    """Hungarian matching maximising IoU; pairs with IoU 0 are dropped. Returns (pred, gt)."""
    if iou.size == 0:
        return []
    rows, cols = linear_sum_assignment(-iou)
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if iou[r, c] > 0]


def mask_boxes_xyxy(masks: Tensor) -> Tensor:
    """Tight boxes ``[x0, y0, x1, y1]`` of boolean masks, in pixel-edge coordinates.

    Pixel ``i`` spans ``[i, i + 1)``, so a mask that covers columns 3..6 has
    ``x0 = 3, x1 = 7``.

    Args:
        masks: (..., H, W) bool.

    Returns:
        (..., 4) float32; zeros for empty masks.

    Example:
        >>> m = torch.zeros(1, 5, 8, dtype=torch.bool)
        >>> m[0, 2:4, 3:7] = True
        >>> mask_boxes_xyxy(m).tolist()
        [[3.0, 2.0, 7.0, 4.0]]
    """
    H, W = masks.shape[-2:]
    rows, cols = masks.any(-1), masks.any(-2)
    ar_h = torch.arange(H, device=masks.device)
    ar_w = torch.arange(W, device=masks.device)
    big = max(H, W) + 1
    x0 = torch.where(cols, ar_w, big).amin(-1)
    x1 = torch.where(cols, ar_w, -1).amax(-1) + 1
    y0 = torch.where(rows, ar_h, big).amin(-1)
    y1 = torch.where(rows, ar_h, -1).amax(-1) + 1
    box = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.float32)
    return torch.where(rows.any(-1, keepdim=True), box, torch.zeros_like(box))


def xyxy_to_xywh(boxes: Tensor) -> Tensor:
    """``[x0, y0, x1, y1]`` -> COCO ``[x, y, w, h]`` (..., 4)."""
    return torch.cat([boxes[..., :2], boxes[..., 2:] - boxes[..., :2]], dim=-1)


def mask_boxes_xywh(masks: Tensor) -> Tensor:
    """Tight COCO boxes ``[x, y, w, h]`` (pixel edges) of boolean masks (..., H, W).

    Zeros for empty masks (:func:`mask_boxes_xyxy`, converted).

    Example:
        >>> m = torch.zeros(1, 5, 8, dtype=torch.bool)
        >>> m[0, 2:4, 3:7] = True
        >>> mask_boxes_xywh(m).tolist()
        [[3.0, 2.0, 4.0, 2.0]]
    """
    return xyxy_to_xywh(mask_boxes_xyxy(masks))
