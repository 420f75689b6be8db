"""The static world around the individuals: a textured ground plane, a wall and a sky.

The ground is the plane z = 0 (tiles of ``tile`` metres in two colours with
smooth colour noise), surrounded by a vertical cylindrical wall of radius
``wall_radius`` and height ``wall_height`` (coloured panels, a dark skirting
band and noise); above the wall is a sky gradient. Ground and wall are shaded
with the scene's :class:`~nsd.synth.shading.Light`; the sky is not. Nothing in
the backdrop moves, so a per-camera median over frames recovers it wherever no
individual stands for most of the time. Cameras must stand inside the wall.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nsd.synth.raycast import intersect_cylinder_inside, intersect_ground
from nsd.synth.shading import Light, lambert
from nsd.synth.texture import smooth_noise

__all__ = ["Backdrop", "BackdropHits"]

GROUND, WALL, SKY = 0, 1, 2


@dataclass(frozen=True)
class BackdropHits:
    """Backdrop seen along rays.

    Attributes:
        rgb: shaded colour in [0, 1], (R, 3).
        distance: distance along the unit ray, (R,); inf for the sky.
        surface: 0 ground, 1 wall, 2 sky; int64 (R,).
    """

    rgb: Tensor
    distance: Tensor
    surface: Tensor


@dataclass(frozen=True)
class Backdrop:
    """Ground, wall and sky (see the module docstring).

    Attributes:
        wall_radius: radius of the wall, metres.
        wall_height: height of the wall, metres.
        tile: side of the ground tiles, metres.
        seed: seed of the colour noise and of the wall's panel colours.
    """

    wall_radius: float = 9.0
    wall_height: float = 3.5
    tile: float = 0.5
    seed: int = 0

    def ground_albedo(self, points: Tensor) -> Tensor:
        """Albedo of ground points (N, 3) -> (N, 3)."""
        p = points.to(torch.float64)
        ij = torch.floor(p[:, :2] / self.tile)
        odd = ((ij[:, 0] + ij[:, 1]) % 2)[:, None]
        a = torch.tensor([0.55, 0.52, 0.45], dtype=p.dtype)
        b = torch.tensor([0.42, 0.44, 0.40], dtype=p.dtype)
        colour = a + odd * (b - a)
        n = 1.0 + 0.12 * smooth_noise(p, self.seed, "ground", 1.5)
        n = n + 0.05 * smooth_noise(p, self.seed, "ground-fine", 0.15)
        return (colour * n[:, None]).clamp(0, 1).to(points.dtype)

    def wall_albedo(self, points: Tensor, panels: int = 16) -> Tensor:
        """Albedo of wall points (N, 3) -> (N, 3): panels by angle, a band, noise."""
        p = points.to(torch.float64)
        angle = torch.atan2(p[:, 1], p[:, 0])
        k = torch.floor((angle + torch.pi) / (2 * torch.pi) * panels).clamp(0, panels - 1).long()
        g = torch.Generator().manual_seed(self.seed + 1)
        palette = 0.35 + 0.45 * torch.rand(panels, 3, generator=g, dtype=p.dtype)
        colour = palette[k]
        band = ((p[:, 2] > 0.8) & (p[:, 2] < 1.0)) | (p[:, 2] < 0.12)
        colour = torch.where(band[:, None], colour * 0.35, colour)
        n = 1.0 + 0.1 * smooth_noise(p, self.seed, "wall", 0.6)
        return (colour * n[:, None]).clamp(0, 1).to(points.dtype)

    def sky(self, directions: Tensor) -> Tensor:
        """Sky colour along unit directions (N, 3) -> (N, 3)."""
        t = directions[:, 2:3].clamp(0, 1)
        low = torch.tensor([0.85, 0.88, 0.92], dtype=directions.dtype)
        high = torch.tensor([0.45, 0.6, 0.85], dtype=directions.dtype)
        return low + t * (high - low)

    def cast(self, origins: Tensor, directions: Tensor, light: Light) -> BackdropHits:
        """Shade the backdrop along rays.

        Args:
            origins: (R, 3). directions: unit, (R, 3).
            light: the scene light.
        """
        sg = intersect_ground(origins, directions)
        sw = intersect_cylinder_inside(origins, directions, self.wall_radius)
        zw = origins[:, 2] + sw * directions[:, 2]
        sw = torch.where((zw >= 0) & (zw <= self.wall_height), sw, torch.full_like(sw, torch.inf))
        surface = torch.full_like(sg, SKY, dtype=torch.int64)
        surface[sw < torch.inf] = WALL
        surface[(sg < sw) & (sg < torch.inf)] = GROUND
        distance = torch.minimum(sg, sw)
        rgb = self.sky(directions)
        for sid in (GROUND, WALL):
            m = surface == sid
            if not m.any():
                continue
            x = origins[m] + distance[m, None] * directions[m]
            if sid == GROUND:
                albedo, normal = self.ground_albedo(x), torch.zeros_like(x)
                normal[:, 2] = 1.0
            else:
                albedo = self.wall_albedo(x)
                normal = torch.zeros_like(x)
                normal[:, :2] = -x[:, :2] / x[:, :2].norm(dim=-1, keepdim=True)
            rgb[m] = lambert(albedo, normal, light)
        return BackdropHits(rgb=rgb, distance=distance, surface=surface)
