"""Small vector helpers shared by inference, export and re-identification."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["unit_vectors", "up_frame", "wrap_angle"]


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Angles (radians) wrapped to [-pi, pi), any shape.

    Example:
        >>> round(wrap_angle(3 * np.pi / 2), 6), round(wrap_angle(-np.pi), 6)
        (-1.570796, -3.141593)
    """
    return (a + np.pi) % (2 * np.pi) - np.pi


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


def up_frame(up: Tensor) -> Tensor:
    """Right-handed orthonormal basis whose last axis is ``up``: columns
    :math:`(e_1, e_2, u)`, :math:`e_1` the world x axis (y when ``up`` is within ~25 degrees
    of x) made orthogonal to :math:`u`, :math:`e_2 = u \\times e_1`.

    Shape:
        (3,) -> (3, 3), in ``up``'s dtype.

    Example:
        >>> up_frame(torch.tensor([0.0, 0.0, 1.0])).tolist()
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    u = up / up.norm()
    a = torch.zeros_like(u)
    a[0 if abs(float(u[0])) < 0.9 else 1] = 1.0
    e1 = a - (a @ u) * u
    e1 = e1 / e1.norm()
    return torch.stack([e1, torch.linalg.cross(u, e1), u], 1)
