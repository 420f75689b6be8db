"""Accuracy measures of rendered maps: silhouette, NNOPCS, depth and colour.

* Silhouette IoU per view.
* NNOPCS MSE (NeTePu table 1) and depth MAE, over the pixels that are
  foreground in both the ground truth and the render (where both maps are
  defined); the share of ground-truth pixels this covers is the recall
  implied by the IoU.
* Colour PSNR over the pixels of a mask (the texture renderer, ours), and over the whole
  8-bit image as NeTePu's test script prepares it (:func:`image_psnr`).

Keypoint errors: :mod:`nsd.evaluation.pose`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["colour_psnr", "depth_mae", "image_psnr", "nnopcs_mse", "silhouette_iou"]


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


def _to_8bit(colour: Tensor) -> Tensor:
    """Colours in [0, 1] -> 8-bit values as the reference stores them (clamped, truncated;
    a colour that was an 8-bit value divided by 255 gets that value back)."""
    return (colour.double().clamp(0, 1) * 255 + 1e-6).floor()


def image_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """PSNR (dB) per image over all pixels, NeTePu's test protocol.

    The reference's test script renders every pixel, stores the render as 8 bits
    (truncated) with zeros outside the ground-truth mask, and compares it with the
    whole 8-bit ground-truth image, background included. Where the background is
    black (the synthetic world's views) this equals :func:`colour_psnr` raised by
    ``10 log10(H W / |mask|)`` up to the 8-bit rounding: the protocols rank models
    alike, only the offset changes with the share of the image the body covers.

    Args:
        pred: (n, H, W, 3) render in [0, 1] (values outside the mask are ignored).
        target: (n, H, W, 3) ground-truth image in [0, 1], background included.
        mask: (n, H, W) bool, the ground-truth mask.

    Returns:
        (n,) float64.
    """
    rec = _to_8bit(pred) * mask[..., None]
    mse = ((rec - _to_8bit(target)) / 255).pow(2).flatten(1).mean(1)
    return 10 * torch.log10(1.0 / mse.clamp(min=1e-12))
