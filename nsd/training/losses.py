r"""Image losses for Bi-NVS: residual-weighted pixel loss and SSIM.

NSD's loss is an L2 pixel loss plus a perceptual loss on ImageNet ResNet-18
features (weight 2). ImageNet weights cannot be downloaded on our machines, so
the structural term is SSIM (``1 - SSIM``, a label-free, weight-free measure of
local structure; :func:`nsd.ops.ssim.ssim_map`, kornia's convention computed by matrix
products, which is faster than kornia's depthwise convolutions and scales with threads);
the ablation table shows what it adds over the pixel loss alone.

The pixel loss can be weighted by the *background residual*: with the
per-camera median background :math:`B`, pixels where :math:`|I - B|` is large
are where the subjects are, and a plain MSE is dominated by the ~95 % of
pixels that the background already explains (the first probe's failure mode).

.. math::
    e(x) = \mathrm{clip}\big(\tfrac{\operatorname{mean}_c |I - B| - \tau}{\kappa}, 0, 1\big),
    \qquad w(x) = 1 + \alpha\,e(x),

    L_{pix} = \frac{\sum_x w(x) \|\hat I(x) - I(x)\|^2}{\sum_x w(x)}.

:math:`e` is :func:`nsd.cues.evidence.foreground_evidence`; it is also the target of the
optional foreground-evidence prior on the composited coverage :math:`1 - T(\infty)`
(see :mod:`nsd.model.bi_nvs`).
"""

from __future__ import annotations

from torch import Tensor

from nsd.ops.ssim import ssim_map

__all__ = ["pixel_loss", "renormalise_to_target", "structural_loss"]


def renormalise_to_target(pred: Tensor, target: Tensor, eps: float = 1e-4) -> Tensor:
    """Give each predicted image the target's per-channel mean and std (NSD reference code)."""
    pm, ps = pred.mean((-2, -1), keepdim=True), pred.std((-2, -1), keepdim=True)
    tm, ts = target.mean((-2, -1), keepdim=True), target.std((-2, -1), keepdim=True)
    return (pred - pm) / (ps + eps) * ts + tm


def pixel_loss(pred: Tensor, target: Tensor, weight: Tensor | None = None) -> Tensor:
    """Weighted mean squared error.

    Args:
        pred, target: (B, C, H, W).
        weight: (B, H, W) non-negative pixel weights, or None for plain MSE.
    """
    err = (pred - target).pow(2).mean(1)
    if weight is None:
        return err.mean()
    return (err * weight).sum() / weight.sum().clamp_min(1e-8)


def structural_loss(pred: Tensor, target: Tensor, window: int = 7) -> Tensor:
    """``1 - SSIM``, averaged over pixels and channels; 0 for identical images.

    Args:
        pred, target: (B, C, H, W).
    """
    return 1 - ssim_map(pred, target, window).mean()


def total_image_loss(
    pred: Tensor,
    target: Tensor,
    weight: Tensor | None,
    ssim_weight: float,
    ssim_window: int = 7,
    renormalise: bool = False,
    parts: int = 1,
) -> dict[str, Tensor]:
    """Pixel + structural loss terms for one reconstruction, or the mean of ``parts``.

    Args:
        pred, target: (P * B, C, H, W): ``parts`` equal batches stacked (e.g. both views
            of Bi-NVS' pairs).
        weight: (P * B, H, W) pixel weights, or None.
        parts: the weighted pixel loss is normalised within each part and the parts'
            losses averaged; the structural loss, a plain mean, is the same either way.
    """
    if pred.shape[0] % parts:
        raise ValueError(f"{pred.shape[0]} images cannot be {parts} equal parts")
    p = renormalise_to_target(pred, target) if renormalise else pred
    weights = (None,) * parts if weight is None else weight.chunk(parts)
    pixel = [pixel_loss(a, b, w)
             for a, b, w in zip(p.chunk(parts), target.chunk(parts), weights, strict=True)]
    out = {"pixel": sum(pixel) / parts}
    if ssim_weight > 0:
        out["ssim"] = structural_loss(pred, target, ssim_window)
    return out


__all__ += ["total_image_loss"]
