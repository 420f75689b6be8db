r"""Multi-view depth of associated windows: rays through window centres and their midpoints.

The calibration that Bi-NVS already uses to rotate latent clouds also fixes
where two associated windows are in 3D. For window :math:`j` of view :math:`v`
and its associated window :math:`i` of view :math:`w`, the rays through the
window centres, :math:`C_v + s\,d_v` and :math:`C_w + u\,d_w`, pass closest at

.. math::
    \begin{pmatrix} s \\ u \end{pmatrix} =
    \begin{pmatrix} d_v\cdot d_v & -d_v\cdot d_w \\ d_v\cdot d_w & -d_w\cdot d_w \end{pmatrix}^{-1}
    \begin{pmatrix} d_v\cdot(C_w - C_v) \\ d_w\cdot(C_w - C_v) \end{pmatrix},

and the midpoint of the two closest points is the window's 3D position; its
camera-space depth in :math:`v` is the triangulated depth :math:`D_{v,j}`.
Pairs of nearly parallel rays (:math:`|\det| < 10^{-6}`) or points behind a
camera are invalid.

The depth prior built on these depths: :mod:`nsd.priors.depth`.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from nsd.cameras.projection import pixel_to_normalized

__all__ = ["nearest_point_to_rays", "ray_distances", "triangulate_midpoints", "window_rays"]


def window_rays(
    boxes: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor, image_size: tuple[int, int]
) -> tuple[Tensor, Tensor]:
    """World rays through window centres.

    Args:
        boxes: (B, N, 4) normalised windows.
        K, R, t, dist: per-sample cameras (B, 3, 3), (B, 3, 3), (B, 3), (B, n).
        image_size: (H, W) of the frames the boxes refer to.

    Returns:
        origins (B, 3) camera centres and unit directions (B, N, 3), world frame.
    """
    H, W = image_size
    uv = torch.stack([(boxes[..., 2] + 1) * W / 2 - 0.5, (boxes[..., 3] + 1) * H / 2 - 0.5], -1)
    xy = pixel_to_normalized(uv, K, dist)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], -1)
    d = d_cam @ R  # R^T d per row
    origins = -(R.transpose(-1, -2) @ t.unsqueeze(-1)).squeeze(-1)
    return origins, d / d.norm(dim=-1, keepdim=True)


def triangulate_midpoints(
    o1: Tensor, d1: Tensor, o2: Tensor, d2: Tensor, eps: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """Midpoints of closest approach of ray pairs.

    Args:
        o1, o2: origins (B, 3).
        d1, d2: unit directions (B, N, 3) (row j of d2 pairs with row j of d1).

    Returns:
        points (B, N, 3) and valid (B, N) (non-parallel, in front of both cameras).
    """
    b = o2 - o1
    a11 = (d1 * d1).sum(-1)
    a12 = (d1 * d2).sum(-1)
    a22 = (d2 * d2).sum(-1)
    r1 = (d1 * b[:, None]).sum(-1)
    r2 = (d2 * b[:, None]).sum(-1)
    det = a11 * -a22 + a12 * a12
    ok = det.abs() > eps
    safe = torch.where(ok, det, torch.ones_like(det))
    s = (r1 * -a22 + a12 * r2) / safe
    u = (a11 * r2 - a12 * r1) / safe
    p = 0.5 * ((o1[:, None] + s[..., None] * d1) + (o2[:, None] + u[..., None] * d2))
    return p, ok & (s > 0) & (u > 0)


def nearest_point_to_rays(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    r"""The point with the least sum of squared distances to rays :math:`o_i + s\,d_i`:

    .. math::
        \Big(\sum_i I - \hat d_i \hat d_i^\top\Big)\, X
            = \sum_i (I - \hat d_i \hat d_i^\top)\, o_i .

    Args:
        origins, directions: (n, 3), n >= 2 rays that are not all parallel.

    Returns:
        (3,) float64.

    Raises:
        ValueError: fewer than two rays, or (nearly) parallel rays.
    """
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    if o.shape != d.shape or o.ndim != 2 or o.shape[1] != 3 or len(o) < 2:
        raise ValueError(f"nearest_point_to_rays: (n >= 2, 3) rays, got {o.shape}, {d.shape}")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (n, 3, 3)
    A, b = proj.sum(0), (proj @ o[:, :, None]).sum(0)[:, 0]
    if np.linalg.cond(A) > 1e8:
        raise ValueError("nearest_point_to_rays: the rays are (nearly) parallel")
    return np.linalg.solve(A, b)


def ray_distances(o1: Tensor, d1: Tensor, o2: Tensor, d2: Tensor, eps: float = 1e-9) -> Tensor:
    r"""Distance between every ray of view 1 and every ray of view 2 (epipolar consistency).

    Args:
        o1, o2: origins (B, 3); d1 (B, N, 3), d2 (B, M, 3) unit directions.

    Returns:
        (B, N, M): :math:`|(o_2 - o_1) \\cdot (d_1 \times d_2)| / |d_1 \times d_2|`, or the
        point-to-line distance for parallel rays.
    """
    b = (o2 - o1)[:, None, None]  # (B, 1, 1, 3)
    c = torch.cross(
        d1[:, :, None].expand(-1, -1, d2.shape[1], -1),
        d2[:, None].expand(-1, d1.shape[1], -1, -1),
        dim=-1,
    )
    n = c.norm(dim=-1)
    skew = (b * c).sum(-1).abs() / n.clamp_min(eps)
    along = (b * d1[:, :, None]).sum(-1, keepdim=True) * d1[:, :, None]
    parallel = (b - along).norm(dim=-1)
    return torch.where(n > 1e-6, skew, parallel)


