r"""The texture VAE's networks: encoder, decoder and colour renderer (NeTePu sec. 3.2).

Encoder (:class:`TextureEncoder`)
    A ResNet-like CNN (BatchNorm, ReLU; ``2 x len(widths)`` basic blocks, ~20
    convolutions, NeTePu: 23) with global average pooling and two dense
    layers giving :math:`\mu` and :math:`\log\sigma^2`. Training samples
    :math:`z = \mu + \sigma \epsilon` (:func:`reparameterise`); inference
    uses :math:`\mu` (the reference stores a sample).

Decoder and renderer (:class:`TextureDecoder`, :class:`ColourRenderer`)
    :math:`z_{texture} \mapsto f_{texture} \in \mathbb{R}^{K \times d_f}`
    (an MLP, eq. 3). The colour renderer is the geometry renderer's class
    (:class:`netepu.geometry.renderer.NeuralRenderer2D`: same view frame, 2D blocks
    and factorised VCA) with a 3-channel colour head; its keypoint features
    are the frozen geometry features :math:`f` concatenated with
    :math:`f_{texture}` and its global code is :math:`[z, z_{texture}]`
    (``renderer_geometry: false``: :math:`f_{texture}` and :math:`z_{texture}`
    only, as NeTePu's code does). The ablation without local texture features
    (``local_features: false``) keeps only :math:`f`, so the texture reaches the
    renderer through the global token alone (with neither, the keypoints carry
    their positions only). Only foreground pixels are ever rendered.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from netepu.geometry.renderer import NeuralRenderer2D, RenderContext, RenderHead, to_frame

__all__ = ["ColourRenderer", "TextureDecoder", "TextureEncoder"]


# ----------------------------------------------------------------------------- networks
class _BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.b1 = nn.BatchNorm2d(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.b2 = nn.BatchNorm2d(cout)
        self.skip = (
            nn.Identity()
            if stride == 1 and cin == cout
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
        )

    def forward(self, x: Tensor) -> Tensor:
        y = self.b2(self.c2(torch.relu(self.b1(self.c1(x)))))
        return torch.relu(y + self.skip(x))


class TextureEncoder(nn.Module):
    """CNN (masked RGB, mask[, NNOPCS]) crop -> (mu, logvar) (eq. 2).

    Args:
        in_channels: 7 with NNOPCS, 4 without.
        latent: d_z.
        widths: channels of the stages (each halves the resolution after the first).
        blocks_per_stage: basic blocks per stage.
        dense_hidden: width of the first dense layer.

    Shape:
        (B, C_in, S, S) -> ((B, d_z), (B, d_z)).
    """

    def __init__(
        self,
        in_channels: int,
        latent: int,
        widths: list[int],
        blocks_per_stage: int = 2,
        dense_hidden: int = 256,
    ) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, widths[0], 3, 1, 1, bias=False),
            nn.BatchNorm2d(widths[0]),
            nn.ReLU(),
        )
        layers, cin = [], widths[0]
        for i, w in enumerate(widths):
            for j in range(blocks_per_stage):
                layers.append(_BasicBlock(cin, w, 2 if (j == 0 and i > 0) else 1))
                cin = w
        self.blocks = nn.Sequential(*layers)
        self.dense = nn.Sequential(
            nn.Linear(cin, dense_hidden), nn.ReLU(), nn.Linear(dense_hidden, 2 * latent)
        )
        self.latent = latent

    def features(self, x: Tensor) -> Tensor:
        """Pooled CNN features, (B, widths[-1])."""
        return self.blocks(self.stem(x)).mean(dim=(2, 3))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        out = self.dense(self.features(x))
        return out[:, : self.latent], out[:, self.latent :]


class TextureDecoder(nn.Module):
    """z_texture (B, d_z) -> per-keypoint texture features f_texture (B, K, d_f) (eq. 3)."""

    def __init__(self, latent: int, n_keypoints: int, features: int, hidden: int = 256) -> None:
        super().__init__()
        self.k, self.f = n_keypoints, features
        self.mlp = nn.Sequential(
            nn.Linear(latent, hidden), nn.ReLU(), nn.Linear(hidden, n_keypoints * features)
        )

    def forward(self, z: Tensor) -> Tensor:
        return self.mlp(z).view(-1, self.k, self.f)


class ColourRenderer(NeuralRenderer2D):
    """The geometry renderer's architecture with a 3-channel colour head (eq. 4).

    Same arguments as :class:`NeuralRenderer2D` (``shared_head`` is ignored).
    :meth:`query` returns ``{"colour": (B, Q, 3)}`` (unclamped).
    """

    def __init__(self, features: int, latent: int, radius: float, **kw: Any) -> None:
        kw = {k: v for k, v in kw.items() if k != "shared_head"}
        super().__init__(features, latent, radius, **kw)
        width = self.down.out_features
        hh, hb = kw.get("head_hidden", 64), kw.get("head_blocks", 3)
        self.heads = nn.ModuleList([RenderHead(width, hh, hb, 3)])

    def query(self, ctx: RenderContext, uv: Tensor) -> dict[str, Tensor]:
        y = self.vca(ctx.prepared, to_frame(uv, ctx.frame))
        return {"colour": self.heads[0](y)}
