r"""Training points: near-boundary and far silhouette points, in-mask points for depth and NNOPCS.

NePu supervises a few pixels per view instead of full maps (NeTePu sec. 5.1):
1500 silhouette points, half *near* the silhouette boundary and half *far*,
and 500 points drawn uniformly inside the ground-truth mask for depth and
NNOPCS.

Boundary pixels (:func:`boundary_pixels`) are the pixels with a 4-neighbour of
the other label, on both sides of the contour. *Near* points are boundary
pixels moved by a rounded Gaussian offset of ``sigma_near`` pixels per axis,
so they straddle the contour (the reference code's sampler meant to do this
but never hits the boundary). *Far* points are uniform over the *region* the
renderer evaluates at test time (the dilated keypoint hull of
:func:`netepu.geometry.maps.candidate_region`), so training covers every pixel a render
may query. Points are integer pixel centres, so their labels are exact.

All functions take a ``numpy.random.Generator`` (the trainer's data RNG, saved
in checkpoints for exact resume).
"""

from __future__ import annotations

import numpy as np

__all__ = ["boundary_pixels", "sample_foreground_points", "sample_silhouette_points"]


def boundary_pixels(mask: np.ndarray) -> np.ndarray:
    """Pixels with a 4-neighbour of the other label.

    Args:
        mask: silhouette, (H, W) bool.

    Returns:
        int64 pixel coordinates ``(x, y)``, (M, 2); empty when the mask is
        all background or all foreground.

    Example:
        >>> m = np.zeros((3, 4), bool); m[:, 2:] = True
        >>> boundary_pixels(m)[:, 0].tolist()
        [1, 2, 1, 2, 1, 2]
    """
    m = np.asarray(mask, bool)
    edge = np.zeros_like(m)
    dx = m[:, 1:] != m[:, :-1]
    dy = m[1:, :] != m[:-1, :]
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    edge[1:, :] |= dy
    edge[:-1, :] |= dy
    ys, xs = np.nonzero(edge)
    return np.stack([xs, ys], -1).astype(np.int64)


def _uniform(pixels: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return pixels[rng.integers(0, len(pixels), n)]


def sample_silhouette_points(
    mask: np.ndarray,
    n_near: int,
    n_far: int,
    rng: np.random.Generator,
    sigma_near: float = 1.0,
    region: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Silhouette supervision points: ``n_near`` straddling the boundary, ``n_far`` in ``region``.

    Args:
        mask: ground-truth silhouette, (H, W) bool.
        n_near: points near the boundary.
        n_far: points uniform in ``region``.
        rng: random generator.
        sigma_near: std of the near points' offset from a boundary pixel, pixels.
        region: where far points may fall, (H, W) bool (default: everywhere).
            The mask's own pixels are added to it.

    Returns:
        ``(uv, label)``: pixel centres (n_near + n_far, 2) float32 as ``(x, y)``
        and labels (n,) float32 in {0, 1}. Without a boundary, near points are
        drawn like far points.
    """
    m = np.asarray(mask, bool)
    h, w = m.shape
    reg = m.copy() if region is None else (np.asarray(region, bool) | m)
    if region is None:
        reg[:] = True
    ys, xs = np.nonzero(reg)
    region_px = np.stack([xs, ys], -1)
    far = _uniform(region_px, n_far, rng)
    edge = boundary_pixels(m)
    if len(edge):
        near = _uniform(edge, n_near, rng) + np.rint(rng.normal(0, sigma_near, (n_near, 2)))
        near = np.clip(near, 0, [w - 1, h - 1]).astype(np.int64)
    else:
        near = _uniform(region_px, n_near, rng)
    uv = np.concatenate([near, far], 0)
    label = m[uv[:, 1], uv[:, 0]].astype(np.float32)
    return uv.astype(np.float32), label


def sample_foreground_points(mask: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` pixel centres drawn uniformly (with replacement) inside the mask.

    Args:
        mask: (H, W) bool with at least one foreground pixel.

    Returns:
        ``(x, y)`` pixel centres, (n, 2) float32.

    Raises:
        ValueError: on an empty mask.
    """
    ys, xs = np.nonzero(np.asarray(mask, bool))
    if len(xs) == 0:
        raise ValueError("cannot sample foreground points from an empty mask")
    i = rng.integers(0, len(xs), n)
    return np.stack([xs[i], ys[i]], -1).astype(np.float32)
