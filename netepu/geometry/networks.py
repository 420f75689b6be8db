r"""Geometry encoder and decoder: K 3D keypoints -> global code z -> keypoints + local features f.

NePu's geometry pipeline (NeTePu sec. 3.1, fig. 1 top):

Encoder
    Keypoints are centred on their centroid :math:`c` and scaled by
    :math:`1 / (2 r)` (``r`` the species' body radius, as NePu scales them);
    every keypoint carries its one-hot identity as feature. Point-transformer
    blocks with full attention and element-wise MLPs, a per-token MLP and a max
    pool over keypoints give the global code :math:`z \in \mathbb{R}^{d_z}`.
    (NePu does not centre; centring makes ``z`` independent of where the
    individual stands, and :math:`c` travels with ``z`` as its translation.)

Decoder
    :math:`z \mapsto` keypoint positions (MLP with a bottleneck, ``K x 3``) and
    per-keypoint features (MLP, ``K x d_f``), refined by point-transformer
    blocks at the decoded positions. World keypoints are
    :math:`c + 2 r\,\hat x`. The blocks see the positions without gradient:
    otherwise the render losses, through the blocks' positional encoding,
    swamp the keypoint loss in the position MLP, whose ReLUs then die, and ``z``
    stops encoding the pose (observed on the synthetic cows at lr 2e-3).

Both are permutation-equivariant over keypoints except through the identity
features: permuting keypoints *and* their identities leaves ``z`` unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from netepu.geometry.attention import PointTransformerBlock

__all__ = [
    "GeometryCode",
    "KeypointDecoder",
    "KeypointEncoder",
    "denormalise_keypoints",
    "normalise_keypoints",
]


def normalise_keypoints(keypoints: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Centre keypoints on their centroid and scale by 1 / (2 radius).

    Args:
        keypoints: world keypoints, shape (B, K, 3).
        radius: body radius r (scene units).

    Returns:
        ``(normalised, centre)``: shapes (B, K, 3) and (B, 3).
    """
    centre = keypoints.mean(dim=1)
    return (keypoints - centre.unsqueeze(1)) / (2.0 * radius), centre


def denormalise_keypoints(normalised: Tensor, centre: Tensor, radius: float) -> Tensor:
    """Inverse of :func:`normalise_keypoints`: (B, K, 3), (B, 3) -> world (B, K, 3)."""
    return normalised * (2.0 * radius) + centre.unsqueeze(1)


@dataclass
class GeometryCode:
    """What the geometry pipeline knows about one posed individual.

    Attributes:
        z: global code, (B, d_z).
        centre: translation c of the individual (keypoint centroid), (B, 3).
        keypoints: decoded world keypoints, (B, K, 3).
        features: per-keypoint local features f, (B, K, d_f).
    """

    z: Tensor
    centre: Tensor
    keypoints: Tensor
    features: Tensor


class KeypointEncoder(nn.Module):
    """Keypoints (+ one-hot identity) -> global code z.

    Args:
        n_keypoints: K.
        width: C of the point-transformer blocks.
        latent: d_z.
        n_blocks: full-attention blocks (NePu: 1 + 4).
        n_freq: Fourier bands of the positional encoding.
        groups: attention groups (default: one per channel, as NePu).

    Shape:
        normalised keypoints (B, K, 3) -> z (B, d_z).
    """

    def __init__(
        self,
        n_keypoints: int,
        width: int = 64,
        latent: int = 256,
        n_blocks: int = 3,
        n_freq: int = 5,
        groups: int | None = None,
    ) -> None:
        super().__init__()
        self.n_keypoints = n_keypoints
        self.embed_id = nn.Linear(n_keypoints, width)
        self.blocks = nn.ModuleList(
            PointTransformerBlock(width, 3, k=0, n_freq=n_freq, groups=groups,
                                  elementwise_mlp=True)
            for _ in range(n_blocks)
        )
        self.out = nn.Sequential(nn.Linear(width, latent), nn.ReLU(), nn.Linear(latent, latent))

    def forward(self, keypoints: Tensor, identity: Tensor | None = None) -> Tensor:
        """Encode.

        Args:
            keypoints: normalised keypoints, (B, K, 3).
            identity: one-hot identities (B, K, K); default the identity matrix
                (keypoint ``j`` has identity ``j``).
        """
        B, K, _ = keypoints.shape
        if K != self.n_keypoints:
            raise ValueError(f"encoder built for {self.n_keypoints} keypoints, got {K}")
        if identity is None:
            identity = torch.eye(K, dtype=keypoints.dtype, device=keypoints.device).expand(B, K, K)
        x = self.embed_id(identity)
        for block in self.blocks:
            x = block(keypoints, x)
        return self.out(x).max(dim=1).values


class KeypointDecoder(nn.Module):
    """Global code z -> normalised keypoints and per-keypoint features f.

    Args:
        n_keypoints: K.
        latent: d_z.
        features: d_f.
        bottleneck: width of the position MLP's bottleneck (NePu: 128).
        n_blocks: point-transformer blocks refining the features (NePu: 3,
            the first with k = 8 neighbours, then full attention).
        k_first: neighbours of the first block.
        n_freq: Fourier bands.
        groups: attention groups (default C).

    Shape:
        z (B, d_z) -> keypoints (B, K, 3), features (B, K, d_f).
    """

    def __init__(
        self,
        n_keypoints: int,
        latent: int = 256,
        features: int = 64,
        bottleneck: int = 128,
        n_blocks: int = 3,
        k_first: int = 8,
        n_freq: int = 5,
        groups: int | None = None,
    ) -> None:
        super().__init__()
        self.n_keypoints, self.n_features = n_keypoints, features
        self.mlp_pos = nn.Sequential(
            nn.Linear(latent, bottleneck), nn.ReLU(), nn.Linear(bottleneck, latent), nn.ReLU(),
            nn.Linear(latent, n_keypoints * 3),
        )
        self.mlp_feats = nn.Sequential(
            nn.Linear(latent, 2 * latent), nn.ReLU(), nn.Linear(2 * latent, 4 * latent),
            nn.ReLU(), nn.Linear(4 * latent, n_keypoints * features),
        )
        self.blocks = nn.ModuleList(
            PointTransformerBlock(features, 3, k=k_first if i == 0 else 0, n_freq=n_freq,
                                  groups=groups)
            for i in range(n_blocks)
        )

    def forward(self, z: Tensor, z_features: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Decode.

        Args:
            z: global code, (B, d_z).
            z_features: the code the features are decoded from (default ``z``;
                training passes ``z.detach()`` to keep render losses out of the
                encoder, see :meth:`netepu.geometry.model.GeometryModel.encode`).
        """
        B = z.shape[0]
        pos = self.mlp_pos(z).reshape(B, self.n_keypoints, 3)
        zf = z if z_features is None else z_features
        feats = self.mlp_feats(zf).reshape(B, self.n_keypoints, self.n_features)
        at = pos.detach()  # the position MLP learns from the keypoint loss alone
        for block in self.blocks:
            feats = block(at, feats)
        return pos, feats
