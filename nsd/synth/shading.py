r"""Lambertian shading from one fixed directional light plus ambient light.

.. math::
    I = \rho \, \big(k_a + (1 - k_a) \max(0, n \cdot \ell)\big)

with albedo :math:`\rho \in [0, 1]^3`, unit surface normal ``n``, unit direction
:math:`\ell` *towards* the light and ambient fraction :math:`k_a`. The light
does not move, so the static backdrop renders identically in every frame. No
shadows are cast (a moving shadow would change background pixels outside every
individual's mask).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Light", "lambert"]


@dataclass(frozen=True)
class Light:
    """A directional light.

    Attributes:
        direction: direction towards the light, world (3,) (normalised on use).
        ambient: ambient fraction :math:`k_a` in [0, 1].
    """

    direction: tuple[float, float, float] = (0.4, 0.25, 1.0)
    ambient: float = 0.35

    def unit(self, dtype: torch.dtype = torch.float32) -> Tensor:
        d = torch.tensor(self.direction, dtype=dtype)
        return d / d.norm()


def lambert(albedo: Tensor, normal: Tensor, light: Light) -> Tensor:
    """Shaded colour (see the module docstring).

    Args:
        albedo: (..., 3) in [0, 1].
        normal: unit normals, (..., 3).
        light: the light.

    Returns:
        Colour in [0, 1], (..., 3).
    """
    cos = (normal * light.unit(normal.dtype)).sum(-1, keepdim=True).clamp_min(0.0)
    return albedo * (light.ambient + (1.0 - light.ambient) * cos)
