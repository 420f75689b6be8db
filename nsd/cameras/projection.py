r"""Pinhole projection with OpenCV's lens distortion, in torch: the one copy.

Conventions (OpenCV): a world point :math:`X` maps to camera coordinates
:math:`X_c = R X + t` (``R`` world-to-camera, ``t`` in scene units); the camera
looks along :math:`+z_c`, :math:`x_c` to the right, :math:`y_c` down. Normalised
coordinates :math:`(x, y) = (X_c/Z_c, Y_c/Z_c)` are distorted with
coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``

.. math::
    r^2 = x^2 + y^2,\quad
    \rho = \frac{1 + k_1 r^2 + k_2 r^4 + k_3 r^6}{1 + k_4 r^2 + k_5 r^4 + k_6 r^6}

    x_d = x \rho + 2 p_1 x y + p_2 (r^2 + 2 x^2),\quad
    y_d = y \rho + p_1 (r^2 + 2 y^2) + 2 p_2 x y

and pixels are :math:`u = K (x_d, y_d, 1)^T`, with pixel centres at integer
coordinates and (0, 0) the centre of the top-left pixel.

Fisheye lenses (Kannala-Brandt, ``cv2.fisheye``; anipose's ``fisheye = true``, COLMAP's
OPENCV_FISHEYE) distort the angle from the optical axis instead:

.. math::
    \theta = \arctan r,\quad
    \theta_d = \theta (1 + k_1 \theta^2 + k_2 \theta^4 + k_3 \theta^6 + k_4 \theta^8),\quad
    (x_d, y_d) = \frac{\theta_d}{r} (x, y)

A lens is one vector: OpenCV's coefficients (0, 4, 5, 8, 12 or 14), or a *lens vector* of
:data:`LENS_SIZE` = 15 entries, OpenCV's 14 then the model (0 OpenCV, 1 fisheye with
k1..k4 in the first four entries), which is how a rig with any fisheye camera is batched
(:meth:`nsd.cameras.calibration.CameraRig.stacked`), so that every caller passes ``dist``
unchanged.

Every projection in the toolkit (calibration, synthetic renderer, NeTePu
renderer, inverse rendering) calls these functions; they are differentiable and
work in float32 and float64.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "LENS_SIZE",
    "distort_normalized",
    "fisheye_lens",
    "pixel_to_normalized",
    "project_points",
    "relative_rotation",
    "rotate_points",
    "undistort_normalized",
]

SUPPORTED_DISTORTION_SIZES = (0, 4, 5, 8, 12, 14)
_FULL = 14  # k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y
LENS_SIZE = _FULL + 1  # a lens vector: 14 coefficients and the model (1: fisheye)
FISHEYE_ITERATIONS = 10  # Newton steps of the fisheye inverse (cv2.fisheye uses 10)


def fisheye_lens(k: Tensor) -> Tensor:
    """The lens vector (..., 15) of Kannala-Brandt coefficients ``k`` (..., 4).

    Example:
        >>> fisheye_lens(torch.tensor([0.1, 0.0, 0.0, 0.0])).tolist()[-2:]
        [0.0, 1.0]
    """
    pad = torch.zeros(*k.shape[:-1], _FULL - 4, dtype=k.dtype, device=k.device)
    return torch.cat([k, pad, torch.ones_like(k[..., :1])], dim=-1)


def _split_lens(dist: Tensor) -> tuple[Tensor, Tensor | None]:
    """OpenCV coefficients (..., n) and the fisheye flag (..., 1) (None for plain OpenCV)."""
    if dist.shape[-1] == LENS_SIZE:
        return dist[..., :_FULL], dist[..., _FULL:] > 0.5
    return dist, None


def _fisheye_distort(xy: Tensor, k: Tensor) -> Tensor:
    """Kannala-Brandt distortion of normalised coordinates (..., N, 2), ``k`` (..., 4)."""
    k1, k2, k3, k4 = (k[..., i : i + 1] for i in range(4))
    r = torch.sqrt((xy * xy).sum(-1).clamp_min(torch.finfo(xy.dtype).tiny))
    th = torch.atan(r)
    t2 = th * th
    th_d = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    return xy * (th_d / r).unsqueeze(-1)


def _fisheye_undistort(xy_d: Tensor, k: Tensor) -> Tensor:
    """Invert :func:`_fisheye_distort` (Newton on theta, as ``cv2.fisheye.undistortPoints``)."""
    k1, k2, k3, k4 = (k[..., i : i + 1] for i in range(4))
    tiny = torch.finfo(xy_d.dtype).tiny
    th_d = torch.sqrt((xy_d * xy_d).sum(-1).clamp_min(tiny)).clamp_max(torch.pi / 2)
    th = th_d
    for _ in range(FISHEYE_ITERATIONS):
        t2 = th * th
        f = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - th_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + 9 * t2 * k4)))
        th = th - f / df
    return xy_d * (torch.tan(th) / th_d).unsqueeze(-1)


def _coefficients(dist: Tensor) -> tuple[Tensor, ...]:
    """Split ``dist`` (..., n) into OpenCV's 14 coefficients (k1, k2, p1, p2, k3, k4, k5, k6,
    s1, s2, s3, s4, tau_x, tau_y), zero-padded, each (..., 1)."""
    n = dist.shape[-1]
    if n not in SUPPORTED_DISTORTION_SIZES:
        raise ValueError(
            f"distortion has {n} coefficients; supported: {SUPPORTED_DISTORTION_SIZES} "
            "(OpenCV order k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])"
        )
    pad = torch.zeros(*dist.shape[:-1], _FULL - n, dtype=dist.dtype, device=dist.device)
    full = torch.cat([dist, pad], dim=-1)
    return tuple(full[..., i : i + 1] for i in range(_FULL))


def _tilt(tau_x: Tensor, tau_y: Tensor) -> tuple[Tensor, ...]:
    """The non-zero entries of OpenCV's tilted-sensor matrix (``computeTiltProjectionMatrix``),
    lower triangular: ``[[cx, 0, 0], [-sx sy, cy, 0], [sy, -cy sx, cy cx]]``."""
    cx, sx, cy, sy = torch.cos(tau_x), torch.sin(tau_x), torch.cos(tau_y), torch.sin(tau_y)
    return cx, -sx * sy, cy, sy, -cy * sx, cy * cx


def distort_normalized(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV lens distortion to normalised image coordinates.

    Args:
        xy: undistorted normalised coordinates, shape (..., N, 2).
        dist: coefficients, shape (..., n) with n in {0, 4, 5, 8, 12, 14}, or lens vectors
            (..., 15) (module docstring); broadcast over N.

    Returns:
        Distorted normalised coordinates, shape (..., N, 2).
    """
    dist, fisheye = _split_lens(dist)
    if fisheye is not None:
        return torch.where(fisheye.unsqueeze(-1), _fisheye_distort(xy, dist[..., :4]),
                           distort_normalized(xy, dist))
    if dist.shape[-1] == 0:
        return xy
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = _coefficients(dist)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + r2 * s2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + r2 * s4)
    if dist.shape[-1] == _FULL:  # tilted sensor: the projective map of the tilt matrix
        m00, m10, m11, m20, m21, m22 = _tilt(tx, ty)
        w = m20 * xd + m21 * yd + m22
        xd, yd = m00 * xd / w, (m10 * xd + m11 * yd) / w
    return torch.stack([xd, yd], dim=-1)


def undistort_normalized(xy_d: Tensor, dist: Tensor, iterations: int = 20) -> Tensor:
    """Invert :func:`distort_normalized`: the tilt exactly, the rest by fixed-point
    iteration (as OpenCV's ``undistortPoints``).

    Args:
        xy_d: distorted normalised coordinates, shape (..., N, 2).
        dist: coefficients, shape (..., n), or lens vectors (..., 15).
        iterations: fixed-point steps; 20 reach ~1e-10 for usual lenses.

    Returns:
        Undistorted normalised coordinates, shape (..., N, 2).
    """
    dist, fisheye = _split_lens(dist)
    if fisheye is not None:
        return torch.where(fisheye.unsqueeze(-1), _fisheye_undistort(xy_d, dist[..., :4]),
                           undistort_normalized(xy_d, dist, iterations))
    if dist.shape[-1] == 0:
        return xy_d
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = _coefficients(dist)
    x0, y0 = xy_d[..., 0], xy_d[..., 1]
    if dist.shape[-1] == _FULL:  # undo the tilt: solve the lower-triangular system
        m00, m10, m11, m20, m21, m22 = _tilt(tx, ty)
        a = x0 / m00
        b = (y0 - m10 * a) / m11
        c = (1 - m20 * a - m21 * b) / m22
        x0, y0 = a / c, b / c
    x, y = x0, y0
    for _ in range(iterations):
        r2 = x * x + y * y
        icdist = (1 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + r2 * s2)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + r2 * s4)
        x = (x0 - dx) * icdist
        y = (y0 - dy) * icdist
    return torch.stack([x, y], dim=-1)


def rotate_points(points: Tensor, R: Tensor) -> Tensor:
    """Rotate row-vector points: ``points @ R^T``.

    Args:
        points: shape (..., N, 3).
        R: rotation, shape (..., 3, 3).
    """
    return points @ R.transpose(-1, -2)


def project_points(
    points: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Project world points to pixels.

    Args:
        points: world points, shape (..., N, 3).
        K: intrinsics, shape (..., 3, 3).
        R: world-to-camera rotation, shape (..., 3, 3).
        t: world-to-camera translation, shape (..., 3).
        dist: distortion coefficients, shape (..., n) (the leading dims of the
            points without N), or None.

    Returns:
        ``(uv, depth)``: pixels (..., N, 2) and camera-space depth :math:`Z_c` (..., N).
        Points with :math:`Z_c \\le 0` are behind the camera; their ``uv`` is finite
        (|Z_c| is clamped at 1e-9, 1e-6 in float32) but meaningless: mask them
        with ``depth > 0``.

    Example:
        >>> K = torch.tensor([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
        >>> uv, z = project_points(torch.tensor([[0.0, 0.0, 2.0]]), K, torch.eye(3), torch.zeros(3))
        >>> uv.tolist(), z.tolist()
        ([[50.0, 40.0]], [2.0])
    """
    cam = rotate_points(points, R) + t.unsqueeze(-2)
    z = cam[..., 2]
    eps = 1e-9 if cam.dtype == torch.float64 else 1e-6
    safe = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
    xy = cam[..., :2] / safe.unsqueeze(-1)
    if dist is not None:
        xy = distort_normalized(xy, dist)
    uv = xy @ K[..., :2, :2].transpose(-1, -2) + K[..., :2, 2].unsqueeze(-2)
    return uv, z


def pixel_to_normalized(uv: Tensor, K: Tensor, dist: Tensor | None = None) -> Tensor:
    """Pixels to undistorted normalised coordinates (the ray direction is (x, y, 1)).

    Args:
        uv: pixels, shape (..., N, 2).
        K: intrinsics, shape (..., 3, 3); skew is honoured.
        dist: distortion coefficients, shape (..., n) (the leading dims of the
            points without N), or None.

    Returns:
        Normalised coordinates, shape (..., N, 2).
    """
    fx, fy = K[..., 0, 0].unsqueeze(-1), K[..., 1, 1].unsqueeze(-1)
    cx, cy = K[..., 0, 2].unsqueeze(-1), K[..., 1, 2].unsqueeze(-1)
    s = K[..., 0, 1].unsqueeze(-1)
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - s * y) / fx
    xy = torch.stack([x, y], dim=-1)
    if dist is not None:
        xy = undistort_normalized(xy, dist)
    return xy


def relative_rotation(R_v: Tensor, R_w: Tensor) -> Tensor:
    r"""Rotation taking camera-``v`` coordinates to camera-``w`` coordinates.

    :math:`R_{v \to w} = R_w R_v^T`: a direction :math:`d_v` seen by camera ``v`` is
    :math:`R_{v \to w} d_v` in camera ``w``. NSD rotates its latent point cloud with it.

    Args:
        R_v, R_w: world-to-camera rotations, shape (..., 3, 3).
    """
    return R_w @ R_v.transpose(-1, -2)
