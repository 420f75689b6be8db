r"""SSIM with its Gaussian windows as matrix products.

The structural similarity of two images :math:`x, y` (Wang et al. 2004), per pixel:

.. math::
    \mathrm{SSIM} = \frac{(2\mu_x\mu_y + c_1)(2\sigma_{xy} + c_2)}
                         {(\mu_x^2 + \mu_y^2 + c_1)(\sigma_x^2 + \sigma_y^2 + c_2)},
    \qquad c_1 = (0.01 L)^2,\; c_2 = (0.03 L)^2,

with the local moments :math:`\mu, \sigma` taken under a Gaussian window
(:math:`\sigma_w = 1.5`, ``window`` taps, reflect padding: kornia's convention, so
:func:`ssim_map` equals ``kornia.metrics.ssim`` to rounding; the tests compare both).

The window is separable and the padding is linear, so blurring an ``(H, W)`` image is
:math:`G_H\,X\,G_W^\top` with two banded matrices that hold the Gaussian taps and the
reflection (:func:`reflect_gaussian_matrix`). The five moment images
(:math:`x, y, x^2, y^2, xy`) are blurred by two batched matrix products. On a CPU this is
2x faster than kornia's depthwise convolutions at the training batch (forward and
backward, one thread) and, unlike them, it scales with threads: matrix products are
what a second core speeds up (docs/benchmarks/threads.md). The dense band wastes
multiplications (``window`` of every ``H`` taps are non-zero), which a BLAS does faster
than a depthwise convolution does the useful ones at these sizes (up to a few hundred
pixels a side).
"""

from __future__ import annotations

import functools

import kornia
import torch
from torch import Tensor

__all__ = ["reflect_gaussian_matrix", "ssim_map"]

SIGMA = 1.5  # the Gaussian window's standard deviation in pixels (SSIM's and kornia's)


@functools.lru_cache(maxsize=32)
def _matrix(size: int, window: int, dtype: torch.dtype, device: str) -> Tensor:
    taps = kornia.filters.get_gaussian_kernel1d(window, SIGMA, device=torch.device(device),
                                                dtype=torch.float64)
    r = window // 2
    src = torch.arange(size)[:, None] + torch.arange(window)[None, :] - r  # (size, window)
    src = src.abs()  # reflect at 0: -k -> k
    src = torch.where(src > size - 1, 2 * (size - 1) - src, src)  # reflect at size - 1
    rows = torch.arange(size)[:, None].expand_as(src)
    out = torch.zeros(size, size, dtype=torch.float64, device=device)
    out.index_put_((rows.reshape(-1), src.reshape(-1)), taps.expand(size, window).reshape(-1),
                   accumulate=True)
    return out.to(dtype)


def reflect_gaussian_matrix(size: int, window: int, dtype: torch.dtype = torch.float32,
                            device: torch.device | str = "cpu") -> Tensor:
    """The ``(size, size)`` matrix :math:`G` with :math:`(G v)_i` = the Gaussian-weighted
    mean of ``v`` around ``i`` under reflect padding (row ``i`` sums to 1).

    Args:
        size: length of the axis; must exceed ``window // 2`` (reflect padding).
        window: odd number of taps.

    Raises:
        ValueError: for an even window or an axis too short to reflect.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the SSIM window must be an odd number of pixels, got {window}")
    if size <= window // 2:
        raise ValueError(f"an image side of {size} px is too short for an SSIM window of "
                         f"{window} px (needs more than {window // 2})")
    return _matrix(int(size), int(window), dtype, str(torch.device(device)))


def ssim_map(x: Tensor, y: Tensor, window: int = 7, max_val: float = 1.0,
             eps: float = 1e-12) -> Tensor:
    """SSIM index per pixel and channel.

    Args:
        x, y: images (B, C, H, W) of the same shape and floating dtype.
        window: odd number of Gaussian taps (``sigma = 1.5`` whatever the window).
        max_val: the images' dynamic range :math:`L`.
        eps: added to the denominator (kornia's convention).

    Returns:
        (B, C, H, W), 1 where the images agree.
    """
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"ssim_map needs two (B, C, H, W) images of one shape, got "
                         f"{tuple(x.shape)} and {tuple(y.shape)}")
    h, w = x.shape[-2:]
    gh = reflect_gaussian_matrix(h, window, x.dtype, x.device)
    gw = reflect_gaussian_matrix(w, window, x.dtype, x.device)
    moments = torch.stack([x, y, x * x, y * y, x * y])  # (5, B, C, H, W)
    mu_x, mu_y, xx, yy, xy = gh @ moments @ gw.T
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    mu_xy, mu_xx, mu_yy = mu_x * mu_y, mu_x * mu_x, mu_y * mu_y
    num = (2 * mu_xy + c1) * (2 * (xy - mu_xy) + c2)
    den = (mu_xx + mu_yy + c1) * ((xx - mu_xx) + (yy - mu_yy) + c2)
    return num / (den + eps)
