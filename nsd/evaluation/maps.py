"""Accuracy measures of rendered maps: silhouette, NNOPCS, depth and colour.

* Silhouette IoU per view.
* NNOPCS MSE (NeTePu table 1) and depth MAE, over the pixels that are
  foreground in both the ground truth and the render (where both maps are
  defined); the share of ground-truth pixels this covers is the recall
  implied by the IoU.
* Colour PSNR over the pixels of a mask (the texture renderer).

Keypoint errors: :mod:`nsd.evaluation.pose`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["colour_psnr", "depth_mae", "nnopcs_mse", "silhouette_iou"]


def silhouette_iou(pred: Tensor, target: Tensor) -> Tensor:
    """Intersection over union of boolean masks (..., H, W) -> (...); 1 when both are empty."""
    inter = (pred & target).flatten(-2).sum(-1).double()
    union = (pred | target).flatten(-2).sum(-1).double()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


def nnopcs_mse(pred: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Mean squared NNOPCS error over valid pixels and channels.

    Args:
        pred, target: (..., H, W, 3).
        valid: (..., H, W) bool.

    Returns:
        Scalar (NaN when no pixel is valid).
    """
    d = (pred - target)[valid]
    return (d.double() ** 2).mean()


def depth_mae(pred: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Mean absolute depth error over valid pixels (units of the inputs); scalar."""
    return (pred - target)[valid].double().abs().mean()


def colour_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """PSNR (dB) per image over mask pixels; colours in [0, 1].

    Args:
        pred, target: (n, H, W, 3); mask: (n, H, W) bool.

    Returns:
        (n,) float64.
    """
    err = ((pred.double() - target.double()) ** 2).sum(-1) * mask
    mse = err.flatten(1).sum(1) / (3 * mask.flatten(1).sum(1).clamp(min=1))
    return 10 * torch.log10(1.0 / mse.clamp(min=1e-12))
