r"""NeTePu's texture pipeline: a texture VAE whose decoder is a keypoint-driven colour renderer.

NeTePu sec. 3.2 (fig. 1 bottom), with the geometry pipeline frozen.

The model (:class:`TextureModel`) holds the networks (:mod:`netepu.texture.networks`),
the frozen geometry model and the re-identification whitening; it is built from
:class:`netepu.texture.config.TextureConfig` and loaded from a checkpoint with
:func:`load_texture_model`. Encoding an image: :mod:`netepu.texture.encoding`; loss:
:mod:`netepu.texture.losses`.

Re-identification embedding (:meth:`TextureModel.reid_embedding`)
    :math:`\mu` renders; for retrieval, :math:`u = \mu` (or, with
    ``reid_colour``, :math:`u = [\mu, c]` with the crop's colour statistics
    :math:`c`, :func:`netepu.texture.embedding.colour_statistics`) is mapped by a
    within-class whitening :math:`e = (u - m) P`
    (:func:`netepu.texture.embedding.within_class_whitening`) that the texture stage fits on
    its training codes after training and stores in the model (buffers
    ``reid_mean``, ``reid_projection``; the identity for models without it).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from netepu.geometry.model import GeometryModel, build_geometry_model
from netepu.geometry.renderer import RenderContext
from netepu.texture.config import TextureConfig
from netepu.texture.embedding import colour_statistics
from netepu.texture.networks import ColourRenderer, TextureDecoder, TextureEncoder
from nsd.cameras.batch import CameraBatch
from nsd.core.errors import CheckpointError, ConfigError
from nsd.core.trainer import load_checkpoint

__all__ = ["TextureModel", "build_texture_model", "load_texture_model"]


# ----------------------------------------------------------------------------- model
class TextureModel(nn.Module):
    """Texture encoder + decoder + colour renderer of one species (geometry lives apart).

    Args:
        cfg: the model config.
        n_keypoints: K.
        geometry_features, geometry_latent: d_f and d_z of the geometry model.
        radius: body radius r of the species.
    """

    def __init__(
        self,
        cfg: TextureConfig,
        n_keypoints: int,
        geometry_features: int,
        geometry_latent: int,
        radius: float,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = TextureEncoder(
            4 + cfg.surface_channels,
            cfg.latent,
            list(cfg.widths),
            cfg.blocks_per_stage,
            cfg.dense_hidden,
        )
        self.decoder = (
            TextureDecoder(cfg.latent, n_keypoints, cfg.features, cfg.decoder_hidden)
            if cfg.local_features
            else None
        )
        feats = (geometry_features if cfg.renderer_geometry else 0) + (
            cfg.features if cfg.local_features else 0
        )
        latent = (geometry_latent if cfg.renderer_geometry else 0) + cfg.latent
        try:
            # no keypoint features at all (NeTePu's code without f_texture): a constant 1 per
            # keypoint, so that the keypoints carry their positions only
            self.renderer = ColourRenderer(max(feats, 1), latent, radius, **dict(cfg.renderer))
        except TypeError as e:
            raise ConfigError(f"netepu.texture.model.renderer: {e}") from e
        # re-identification embedding (u - reid_mean) @ reid_projection of the input
        # u = [mu, colour statistics] (netepu.reid's within-class whitening, fitted after
        # training); the identity until then
        self.register_buffer("reid_mean", torch.zeros(cfg.reid_dims))
        self.register_buffer("reid_projection", torch.eye(cfg.reid_dims))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        d = self.cfg.reid_dims  # checkpoints from before the whitening: the identity map
        state_dict.setdefault(prefix + "reid_mean", torch.zeros(d))
        state_dict.setdefault(prefix + "reid_projection", torch.eye(d))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def reid_input(
        self, mu: Tensor, rgb: Tensor | None = None, inside: Tensor | None = None
    ) -> Tensor:
        """What the re-identification whitening reads: mu (B, d_z), with ``reid_colour``
        followed by :func:`netepu.texture.embedding.colour_statistics` of the crop that gave mu (rgb
        (B, S, S, 3) in [0, 1], inside (B, S, S) bool): (B, cfg.reid_dims)."""
        if not self.cfg.reid_colour:
            return mu
        if rgb is None or inside is None:
            raise ValueError(
                "this texture model re-identifies with colour statistics: pass the crop"
            )

        return torch.cat([mu, colour_statistics(rgb, inside).to(mu.dtype)], -1)

    def reid_embedding(
        self, mu: Tensor, rgb: Tensor | None = None, inside: Tensor | None = None
    ) -> Tensor:
        """Re-identification embedding of texture codes mu (B, d_z) encoded from the crop
        rgb, inside (needed with ``reid_colour``; :meth:`reid_input`): (B, cfg.reid_dims)."""
        return self.whiten_reid(self.reid_input(mu, rgb, inside))

    def whiten_reid(self, u: Tensor) -> Tensor:
        """The stored whitening of re-id inputs u (B, reid_dims): (u - m) P, (B, reid_dims)."""
        return (u - self.reid_mean.to(u.dtype)) @ self.reid_projection.to(u.dtype)

    @staticmethod
    def crop_colours(x: Tensor) -> tuple[Tensor, Tensor]:
        """The crop colours (B, S, S, 3) and mask (B, S, S) bool of an encoder input x
        (B, C_in, S, S) (:meth:`encoder_input`)."""
        return x[:, :3].permute(0, 2, 3, 1), x[:, 3] > 0.5

    def set_reid_whitening(self, mean: Tensor | Any, projection: Tensor | Any) -> None:
        """Store a whitening ``(m (D,), P (D, D))`` of the re-id input, D = ``cfg.reid_dims``.

        See :func:`netepu.texture.embedding.within_class_whitening`.
        """
        m = torch.as_tensor(mean, dtype=self.reid_mean.dtype, device=self.reid_mean.device)
        p = torch.as_tensor(
            projection, dtype=self.reid_projection.dtype, device=self.reid_projection.device
        )
        if m.shape != self.reid_mean.shape or p.shape != self.reid_projection.shape:
            raise ValueError(
                f"reid whitening: want shapes {tuple(self.reid_mean.shape)} and "
                f"{tuple(self.reid_projection.shape)}, got {tuple(m.shape)} and {tuple(p.shape)}"
            )
        self.reid_mean.copy_(m)
        self.reid_projection.copy_(p)

    def encoder_input(self, rgb: Tensor, inside: Tensor, nnopcs: Tensor | None) -> Tensor:
        """Crops (B, S, S, 3), (B, S, S) bool, surface (B, S, S, C_s) -> encoder input
        (B, C_in, S, S); C_s = ``cfg.surface_channels`` (NNOPCS [+ world normals])."""
        parts = [rgb, inside[..., None].to(rgb.dtype)]
        if self.cfg.use_nnopcs:
            if nnopcs is None:
                raise ValueError("this texture model reads NNOPCS maps; pass them")
            parts.append(nnopcs * inside[..., None])
        return torch.cat(parts, -1).permute(0, 3, 1, 2).contiguous()

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Encoder input (B, C_in, S, S) -> (mu, logvar), each (B, d_z)."""
        return self.encoder(x)

    def prepare(
        self,
        z_texture: Tensor,
        geometry_z: Tensor,
        geometry_features: Tensor,
        keypoints: Tensor,
        camera: CameraBatch,
    ) -> RenderContext:
        """Per-view colour render context.

        Args:
            z_texture: (B, d_z) texture codes.
            geometry_z, geometry_features: the frozen geometry code, (B, d_zg), (B, K, d_f);
                read only with ``cfg.renderer_geometry``.
            keypoints: world keypoints (B, K, 3) that drive the render.
            camera: per-view camera tensors (batch B).
        """
        feats, code = [], [z_texture]
        if self.cfg.renderer_geometry:
            feats.append(geometry_features)
            code.insert(0, geometry_z)
        if self.decoder is not None:
            feats.append(self.decoder(z_texture))
        if not feats:
            feats.append(keypoints.new_ones(*keypoints.shape[:2], 1))
        return self.renderer.prepare(keypoints, torch.cat(feats, -1), torch.cat(code, -1), camera)

    def query(self, ctx: RenderContext, uv: Tensor) -> Tensor:
        """Colour at query pixels (B, Q, 2) -> (B, Q, 3) (unclamped)."""
        return self.renderer.query(ctx, uv)["colour"]


def build_texture_model(
    cfg: Mapping[str, Any] | TextureConfig, geometry: GeometryModel
) -> TextureModel:
    """Texture model for a geometry model (sizes taken from it)."""
    if not isinstance(cfg, TextureConfig):
        cfg = TextureConfig.from_config(cfg)
    return TextureModel(
        cfg,
        geometry.n_keypoints,
        geometry.decoder.n_features,
        geometry.renderer.down.in_features,
        geometry.radius,
    )


# Keys that texture checkpoints written before the key existed lack, with the behaviour those
# models were trained with (not defaults: a new model takes conf/netepu/texture/default.yaml).
LEGACY_TEXTURE_KEYS = {"use_normals": False, "reid_colour": False, "renderer_geometry": True}


def load_texture_model(
    path: str | os.PathLike,
) -> tuple[TextureModel, GeometryModel, dict[str, Any]]:
    """Load ``(texture, geometry, config)`` from a ``netepu-train stage=texture`` checkpoint.

    Both models are returned in eval mode.
    """

    state = load_checkpoint(path)
    config = state.get("config") or {}
    try:
        net = config["netepu"]
        geometry = build_geometry_model(
            net["model"], int(net["data"]["n_keypoints"]), float(net["data"]["radius"])
        )
        geometry.load_state_dict(state["modules"]["geometry"])
        texture = build_texture_model(
            {**LEGACY_TEXTURE_KEYS, **net["texture"]["model"]}, geometry
        )
        texture.load_state_dict(state["modules"]["texture"])
    except (KeyError, RuntimeError, TypeError) as e:
        raise CheckpointError(f"{path} is not a NeTePu texture checkpoint: {e}") from e
    return texture.eval(), geometry.eval(), config


