r"""Focal spatial transformers (NSD supplement B): crop a window, paste it back.

A window ("box") is ``b = (s_x, s_y, t_x, t_y)`` in normalised image
coordinates (the image spans [-1, 1] on each axis, ``align_corners=False``):
crop coordinate :math:`(u, v) \in [-1, 1]^2` samples image point
:math:`(s_x u + t_x, s_y v + t_y)`. So ``s`` is the window's half-size as a
fraction of the image's half-size (``s = 1``: the whole image) and ``t`` its
centre.

The *focal* transformer multiplies the crop with the C-infinity bump

.. math::
    G(u, v) = \exp\!\Big(1 - \frac{1}{1 - \sqrt{u^4 + v^4}}\Big)
    \ \text{if } \sqrt{u^4 + v^4} < 1, \qquad G = 0 \text{ otherwise,}

so the encoder sees a vignetted crop, and pre-multiplies decoded windows with
``G`` before the inverse warp: :math:`\tilde T(I, b) = T(I, b)\,G`,
:math:`\tilde T^{-1}(b, \bar I) = T^{-1}(b, G \bar I)`. ``G`` is exactly 0 on and
outside the super-ellipse edge (the formula divides by zero at the edge and
exceeds 1 outside it). Values: G(0.5, 0) = 0.72, G(0.8, 0) = 0.17,
G(0.95, 0) = 1e-4. With ``focal=False`` the classical transformer (G = 1) is
used, for the ablation.

The inverse warp has the closed form ``theta^-1 = [[1/s_x, 0, -t_x/s_x],
[0, 1/s_y, -t_y/s_y]]``, safe because the detector bounds ``s >= 0.2``.
Paste-back pads images with their border and masks with zeros.

Both warps are axis-aligned, so their sampling grid is separable: :func:`axis_grid`
builds it from one row of ``x`` and one column of ``y`` per window, the grid
``F.affine_grid`` gives for those ``theta`` without its ``(M, h w, 3) x (M, 3, 2)``
batched product (MKL is slow at that shape: 12 of a training step's 220 ms on one
thread went to it and its gradient).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "axis_grid",
    "box_to_pixels",
    "box_to_theta",
    "crop",
    "focal_bump",
    "focal_bump_at",
    "inverse_theta",
    "paste",
]


def focal_bump_at(x: Tensor, y: Tensor) -> Tensor:
    """The bump ``G`` at crop coordinates ``(x, y)`` (any matching shapes); 0 on/outside edge.

    Example:
        >>> round(focal_bump_at(torch.tensor(0.5), torch.tensor(0.0)).item(), 4)
        0.7165
    """
    r = torch.sqrt((x**4 + y**4).clamp_min(1e-30))  # clamp: finite gradient at the centre
    inside = r < 1
    gap = torch.where(inside, 1 - r, torch.ones_like(r))  # safe value where unused
    return torch.where(inside, torch.exp(1 - 1 / gap), torch.zeros_like(r))


def focal_bump(
    height: int, width: int, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> Tensor:
    """``G`` sampled at the pixel centres of a (height, width) crop: shape (height, width).

    A new tensor each call (from a cached float64 grid: every crop, paste and
    mask normalisation of a step asks for the same one).
    """
    return _bump_grid(int(height), int(width)).to(dtype=dtype, device=device, copy=True)


@functools.lru_cache(maxsize=16)
def _bump_grid(height: int, width: int) -> Tensor:
    ys = (2 * torch.arange(height, dtype=torch.float64) + 1) / height - 1
    xs = (2 * torch.arange(width, dtype=torch.float64) + 1) / width - 1
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return focal_bump_at(gx, gy)


def box_to_theta(boxes: Tensor) -> Tensor:
    """Affine crop matrices of boxes (..., 4) = (sx, sy, tx, ty): shape (..., 2, 3)."""
    sx, sy, tx, ty = boxes.unbind(-1)
    zero = torch.zeros_like(sx)
    return torch.stack([torch.stack([sx, zero, tx], -1), torch.stack([zero, sy, ty], -1)], -2)


def inverse_theta(boxes: Tensor) -> Tensor:
    """Affine paste-back matrices (closed-form inverse of :func:`box_to_theta`): (..., 2, 3)."""
    sx, sy, tx, ty = boxes.unbind(-1)
    zero = torch.zeros_like(sx)
    return torch.stack(
        [torch.stack([1 / sx, zero, -tx / sx], -1), torch.stack([zero, 1 / sy, -ty / sy], -1)], -2
    )


def axis_grid(theta: Tensor, size: tuple[int, int]) -> Tensor:
    """The sampling grid of axis-aligned affine maps at the pixel centres of a ``size``
    output: what ``F.affine_grid(theta, (M, C, *size), align_corners=False)`` gives for
    ``theta = [[a, 0, b], [0, c, d]]`` (the off-diagonal terms are not read).

    Args:
        theta: (M, 2, 3) maps from output coordinates to input coordinates.
        size: output (height, width).

    Returns:
        (M, height, width, 2): ``[..., 0] = a x_j + b`` and ``[..., 1] = c y_i + d`` at
        the output's pixel centres ``x_j = (2 j + 1) / width - 1`` (``y_i`` likewise).
    """
    h, w = size
    M = theta.shape[0]
    xs = (2 * torch.arange(w, dtype=theta.dtype, device=theta.device) + 1) / w - 1
    ys = (2 * torch.arange(h, dtype=theta.dtype, device=theta.device) + 1) / h - 1
    gx = theta[:, 0, 0, None] * xs + theta[:, 0, 2, None]  # (M, w)
    gy = theta[:, 1, 1, None] * ys + theta[:, 1, 2, None]  # (M, h)
    return torch.stack([gx[:, None, :].expand(M, h, w), gy[:, :, None].expand(M, h, w)], -1)


def crop(
    images: Tensor,
    boxes: Tensor,
    size: tuple[int, int],
    focal: bool = True,
    padding_mode: str = "zeros",
) -> Tensor:
    """Crop windows from images (the forward (focal) spatial transformer).

    Args:
        images: (B, C, H, W).
        boxes: (B, N, 4) windows per image (``sx, sy, tx, ty``).
        size: crop (height, width).
        focal: multiply the crops with the bump ``G``.
        padding_mode: ``grid_sample`` padding for windows reaching outside the image.

    Returns:
        Crops, shape (B, N, C, height, width).
    """
    B, N = boxes.shape[:2]
    C = images.shape[1]
    theta = box_to_theta(boxes.reshape(B * N, 4)).to(images.dtype)
    grid = axis_grid(theta, size)
    src = images.unsqueeze(1).expand(B, N, *images.shape[1:]).reshape(B * N, *images.shape[1:])
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode=padding_mode,
                        align_corners=False)
    if focal:
        out = out * focal_bump(*size, dtype=out.dtype, device=out.device)
    return out.reshape(B, N, C, *size)


def paste(
    windows: Tensor,
    boxes: Tensor,
    image_size: tuple[int, int],
    focal: bool = True,
    padding_mode: str = "zeros",
) -> Tensor:
    """Paste windows back into full frames (the inverse (focal) spatial transformer).

    Args:
        windows: (B, N, C, h, w) decoded windows.
        boxes: (B, N, 4) the windows' boxes.
        image_size: output (H, W).
        focal: pre-multiply the windows with the bump ``G`` before warping.
        padding_mode: ``"border"`` for images, ``"zeros"`` for masks (NSD).

    Returns:
        Full-frame layers, shape (B, N, C, H, W).
    """
    B, N, C, h, w = windows.shape
    if focal:
        windows = windows * focal_bump(h, w, dtype=windows.dtype, device=windows.device)
    theta = inverse_theta(boxes.reshape(B * N, 4)).to(windows.dtype)
    grid = axis_grid(theta, image_size)
    out = F.grid_sample(windows.reshape(B * N, C, h, w), grid, mode="bilinear",
                        padding_mode=padding_mode, align_corners=False)
    return out.reshape(B, N, C, *image_size)


def box_to_pixels(boxes: Tensor, image_size: tuple[int, int]) -> Tensor:
    """Boxes (..., 4) to COCO pixel boxes ``[x, y, width, height]`` (pixel-edge coordinates).

    Args:
        boxes: (..., 4) = (sx, sy, tx, ty).
        image_size: (H, W).
    """
    H, W = image_size
    sx, sy, tx, ty = boxes.unbind(-1)
    return torch.stack([(tx - sx + 1) * W / 2, (ty - sy + 1) * H / 2, sx * W, sy * H], -1)
