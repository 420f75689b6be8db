"""Encoder E: a window crop -> appearance vector and 3D latent point cloud (NSD sec. 3.1)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from nsd.model.layers import conv_stack

__all__ = ["Encoder", "rotate_latent"]


class Encoder(nn.Module):
    """Maps crops (B, 3, h, w) to appearance (B, app_dims) and latent cloud (B, points, 3).

    Args:
        crop_size: h = w of the crops.
        widths: channels of the strided conv stages.
        app_dims: appearance vector length (NSD: 128; the first 16 drive association).
        points: size of the 3D latent point cloud (NSD: 200).
    """

    def __init__(self, crop_size: int, widths: tuple[int, ...], app_dims: int, points: int) -> None:
        super().__init__()
        self.app_dims, self.points = app_dims, points
        self.backbone = conv_stack(3, widths)
        feat = crop_size // 2 ** len(widths)
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(widths[-1] * feat * feat, 512),
                                nn.ReLU(inplace=True))
        self.app = nn.Linear(512, app_dims)
        self.geometry = nn.Linear(512, points * 3)

    def forward(self, crops: Tensor) -> tuple[Tensor, Tensor]:
        h = self.fc(self.backbone(crops))
        return self.app(h), self.geometry(h).view(-1, self.points, 3)


def rotate_latent(latent: Tensor, rotation: Tensor) -> Tensor:
    """Rotate latent clouds (B, N, P, 3) by one rotation per sample (B, 3, 3): ``L R^T``."""
    return torch.einsum("bnpk,bjk->bnpj", latent, rotation)
