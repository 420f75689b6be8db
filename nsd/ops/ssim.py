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


def _blur(z: Tensor, gh: Tensor, gw: Tensor) -> Tensor:
    """:math:`G_H Z G_W^\top` over the last two axes."""
    return gh @ z @ gw.T


def _blur_transposed(z: Tensor, gh: Tensor, gw: Tensor) -> Tensor:
    """:math:`G_H^\top Z G_W`, the adjoint of :func:`_blur` (reflection makes G asymmetric)."""
    return gh.T @ z @ gw


class _SSIM(torch.autograd.Function):
    r"""The SSIM map with its gradient written out (one pass of matrix products back).

    With :math:`A_1 = 2\mu_x\mu_y + c_1`, :math:`A_2 = 2\sigma_{xy} + c_2`,
    :math:`B_1 = \mu_x^2 + \mu_y^2 + c_1`, :math:`B_2 = \sigma_x^2 + \sigma_y^2 + c_2`,
    :math:`D = B_1 B_2 + \epsilon` and :math:`S = A_1 A_2 / D`, the map's derivatives by the
    blurred moments are

    .. math::
        \partial S/\partial\mu_x = 2\mu_y (A_2 - A_1)/D - 2\mu_x S (B_2 - B_1)/D,\quad
        \partial S/\partial\overline{x^2} = -S B_1/D,\quad
        \partial S/\partial\overline{xy} = 2A_1/D

    (and :math:`x \leftrightarrow y`), and the gradient of an image is the adjoint blur of
    those, times :math:`1`, :math:`2x` and :math:`y`. Autograd through :func:`_blur` and
    the dozen products would blur all five moments back and keep every intermediate; this
    blurs back the three (four when both images need a gradient) that depend on the
    image. First derivatives only.
    """

    @staticmethod
    def forward(ctx, x, y, gh, gw, c1, c2, eps):
        mu_x, mu_y, xx, yy, xy = _blur(torch.stack([x, y, x * x, y * y, x * y]), gh, gw)
        mu_xy = mu_x * mu_y
        a1, a2 = 2 * mu_xy + c1, 2 * (xy - mu_xy) + c2
        b1 = mu_x * mu_x + mu_y * mu_y + c1
        b2 = (xx + yy) - (b1 - c1) + c2
        d = b1 * b2 + eps
        s = a1 * a2 / d
        ctx.save_for_backward(x, y, gh, gw, mu_x, mu_y, a1, a2, b1, b2, d, s)
        return s

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        x, y, gh, gw, mu_x, mu_y, a1, a2, b1, b2, d, s = ctx.saved_tensors
        need_x, need_y = ctx.needs_input_grad[:2]
        g = grad / d
        first = g * (a2 - a1)  # times 2 mu_other: the mean's derivative, first part
        second = g * s * (b2 - b1)  # times 2 mu_self, second part
        square = -g * s * b1  # the derivative by the blurred square (either image's)
        cross = 2 * g * a1  # by the blurred product xy
        parts = []
        if need_x:
            parts.append(2 * (mu_y * first - mu_x * second))
        if need_y:
            parts.append(2 * (mu_x * first - mu_y * second))
        back = _blur_transposed(torch.stack([*parts, square, cross]), gh, gw)
        square_b, cross_b = back[-2], back[-1]
        gx = gy = None
        if need_x:
            gx = back[0] + 2 * x * square_b + y * cross_b
        if need_y:
            gy = back[1 if need_x else 0] + 2 * y * square_b + x * cross_b
        return gx, gy, None, None, None, None, None


def ssim_map(x: Tensor, y: Tensor, window: int = 7, max_val: float = 1.0,
             eps: float = 1e-12) -> Tensor:
    """SSIM index per pixel and channel.

    Args:
        x, y: images (B, C, H, W) of the same shape and floating dtype.
        window: odd number of Gaussian taps (``sigma = 1.5`` whatever the window).
        max_val: the images' dynamic range :math:`L`.
        eps: added to the denominator (kornia's convention).

    Returns:
        (B, C, H, W), 1 where the images agree. Differentiable once in ``x`` and ``y``
        (the gradient is written out: :class:`_SSIM`).
    """
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"ssim_map needs two (B, C, H, W) images of one shape, got "
                         f"{tuple(x.shape)} and {tuple(y.shape)}")
    h, w = x.shape[-2:]
    gh = reflect_gaussian_matrix(h, window, x.dtype, x.device)
    gw = reflect_gaussian_matrix(w, window, x.dtype, x.device)
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    return _SSIM.apply(x, y, gh, gw, c1, c2, eps)
