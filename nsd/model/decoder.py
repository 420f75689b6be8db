"""Decoder D: (rotated latent cloud, appearance) -> window RGB and mask logit (NSD sec. 3.1).

As in the reference: a linear map of the cloud to a coarse feature grid (with
dropout), the appearance vector broadcast over the grid and concatenated, then
bilinear x2 upsampling stages of 3x3 convolutions, and a 1x1 convolution to
4 channels (RGB through a sigmoid, plus a mask logit). No skip connections.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from nsd.model.layers import upsample_block

__all__ = ["Decoder"]


class Decoder(nn.Module):
    """Renders (B, 3, h, w) RGB in [0, 1] and (B, 1, h, w) mask logits.

    Args:
        crop_size: output h = w (a multiple of 2 ** len(widths)).
        widths: channels of the upsampling stages (coarse to fine).
        app_dims, points: as in the encoder.
        dropout: dropout on the geometry features (NSD: 0.3).
        convs: 3x3 convolutions per stage (NSD: 3).
    """

    def __init__(self, crop_size: int, widths: tuple[int, ...], app_dims: int, points: int,
                 dropout: float, convs: int) -> None:
        super().__init__()
        self.grid = crop_size // 2 ** len(widths)
        self.c0 = widths[0]
        self.fc = nn.Sequential(nn.Linear(points * 3, self.c0 * self.grid**2), nn.Dropout(dropout))
        stages, c = [], self.c0 + app_dims
        for w in widths:
            stages.append(upsample_block(c, w, convs))
            c = w
        self.stages = nn.Sequential(*stages)
        self.out = nn.Conv2d(c, 4, 1)

    def forward(self, latent: Tensor, app: Tensor) -> tuple[Tensor, Tensor]:
        """latent (B, P, 3), app (B, D) -> rgb (B, 3, h, w), mask logit (B, 1, h, w)."""
        g = self.fc(latent.flatten(1)).view(-1, self.c0, self.grid, self.grid)
        a = app[..., None, None].expand(-1, -1, self.grid, self.grid)
        x = self.out(self.stages(torch.cat([g, a], 1)))
        return torch.sigmoid(x[:, :3]), x[:, 3:]
