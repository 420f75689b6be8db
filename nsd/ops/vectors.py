"""Small vector helpers shared by inference, export and re-identification."""

from __future__ import annotations

import numpy as np

__all__ = ["unit_vectors"]


def unit_vectors(x: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """``x`` scaled to unit Euclidean length along its last axis.

    Args:
        x: (..., D).
        eps: lower bound of the norm, so that a zero vector stays zero (no NaN).

    Returns:
        (..., D), the same shape.

    Example:
        >>> unit_vectors(np.array([3.0, 4.0])).tolist()
        [0.6, 0.8]
        >>> unit_vectors(np.zeros(2)).tolist()
        [0.0, 0.0]
    """
    x = np.asarray(x)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), eps)
