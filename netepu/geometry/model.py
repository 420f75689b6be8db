"""The NeTePu geometry pipeline as one module: encoder, decoder and 2D renderer.

:class:`GeometryModel` wires :mod:`netepu.geometry.networks` (keypoints -> ``z`` ->
keypoints + features) to :mod:`netepu.geometry.renderer` (keypoints + features + ``z``
-> silhouette, depth, NNOPCS at query pixels). It is built from the
``netepu/model`` config group (:func:`build_geometry_model`) and loaded from a
trainer checkpoint with :func:`load_geometry_model`.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping
from typing import Any

from torch import Tensor, nn

from netepu.geometry.networks import (
    GeometryCode,
    KeypointDecoder,
    KeypointEncoder,
    denormalise_keypoints,
    normalise_keypoints,
)
from netepu.geometry.renderer import OUTPUTS, NeuralRenderer2D, RenderContext
from nsd.cameras.batch import CameraBatch
from nsd.core.errors import CheckpointError, ConfigError
from nsd.core.trainer import load_checkpoint

__all__ = ["GeometryModel", "build_geometry_model", "geometry_model_from_state",
           "load_geometry_model"]


class GeometryModel(nn.Module):
    """Encoder + decoder + renderer of one species.

    Args:
        encoder, decoder, renderer: the three parts.
        radius: body radius r of the species (scene units).
    """

    def __init__(
        self,
        encoder: KeypointEncoder,
        decoder: KeypointDecoder,
        renderer: NeuralRenderer2D,
        radius: float,
    ) -> None:
        super().__init__()
        self.encoder, self.decoder, self.renderer = encoder, decoder, renderer
        self.radius = float(radius)

    @property
    def n_keypoints(self) -> int:
        return self.encoder.n_keypoints

    def encode(self, keypoints: Tensor, features_reach_encoder: bool = True) -> GeometryCode:
        """World keypoints (B, K, 3) -> :class:`GeometryCode` (z, centre, decoded keypoints, f).

        Args:
            keypoints: world keypoints, (B, K, 3).
            features_reach_encoder: let gradients of the features (hence of the
                render losses) flow into the encoder. The encoder sees only
                keypoints, so ``z`` can hold nothing the keypoints do not; with
                False it is shaped by the keypoint loss alone, a pose code, and
                the render losses train the feature decoder and the renderer
                (training default; NePu trains everything jointly).
        """
        normalised, centre = normalise_keypoints(keypoints, self.radius)
        z = self.encoder(normalised)
        return self.decode(z, centre, None if features_reach_encoder else z.detach())

    def decode(self, z: Tensor, centre: Tensor, z_features: Tensor | None = None) -> GeometryCode:
        """Global code (B, d_z) and translation (B, 3) -> :class:`GeometryCode`.

        ``z_features``: the code the features are decoded from (default ``z``).
        """
        pos, feats = self.decoder(z, z_features)
        return GeometryCode(z, centre, denormalise_keypoints(pos, centre, self.radius), feats)

    def prepare(
        self, code: GeometryCode, camera: CameraBatch, keypoints: Tensor | None = None
    ) -> RenderContext:
        """Per-view render context.

        Args:
            code: the individual's code (batch B = number of views, or 1 to
                broadcast over the views).
            camera: a :class:`nsd.cameras.batch.CameraBatch` of B cameras (or a mapping).
            keypoints: world keypoints (B, K, 3) that drive the render; default
                the decoded ``code.keypoints`` (inverse rendering). Training and
                puppeteering pass the input keypoints.
        """
        kps = code.keypoints if keypoints is None else keypoints
        camera = CameraBatch.from_mapping(camera)
        B = len(camera)
        kps, feats, z = (x.expand(B, *x.shape[1:]) if x.shape[0] == 1 else x
                         for x in (kps, code.features, code.z))
        return self.renderer.prepare(kps, feats, z, camera)

    def query(
        self, ctx: RenderContext, uv: Tensor, outputs: Collection[str] = OUTPUTS
    ) -> dict[str, Tensor]:
        """Render query pixels (B, Q, 2); see :meth:`NeuralRenderer2D.query`."""
        return self.renderer.query(ctx, uv, outputs)


def _section(cfg: Mapping[str, Any], key: str) -> dict[str, Any]:
    if key not in cfg:
        raise ConfigError(f"netepu.model lacks the section '{key}' (encoder, decoder, renderer)")
    return dict(cfg[key])


def build_geometry_model(cfg: Mapping[str, Any], n_keypoints: int, radius: float) -> GeometryModel:
    """Build the model from a ``netepu/model`` config (see ``conf/netepu/model/*.yaml``).

    Args:
        cfg: mapping with ``encoder``, ``decoder`` and ``renderer`` sections.
        n_keypoints: K of the species.
        radius: body radius r (scene units).
    """
    enc, dec, ren = (_section(cfg, k) for k in ("encoder", "decoder", "renderer"))
    try:
        latent = int(enc["latent"])
        encoder = KeypointEncoder(n_keypoints, **enc)
        decoder = KeypointDecoder(n_keypoints, latent=latent, **dec)
        renderer = NeuralRenderer2D(features=int(dec["features"]), latent=latent,
                                    radius=radius, **ren)
    except (TypeError, KeyError, ValueError) as e:
        raise ConfigError(f"netepu.model: {e}") from e
    return GeometryModel(encoder, decoder, renderer, radius)


def load_geometry_model(path: str | os.PathLike) -> tuple[GeometryModel, dict[str, Any]]:
    """Load a geometry model from a ``netepu-train`` checkpoint.

    Returns:
        ``(model, config)``: the model in eval mode and the run's config.
    """

    return geometry_model_from_state(load_checkpoint(path), str(path))


def geometry_model_from_state(state: dict[str, Any], source: str) -> tuple[GeometryModel,
                                                                           dict[str, Any]]:
    """:func:`load_geometry_model` of a checkpoint already loaded (``source`` names it in
    errors)."""
    config = state.get("config") or {}
    try:
        net = config["netepu"]
        model = build_geometry_model(net["model"], int(net["data"]["n_keypoints"]),
                                     float(net["data"]["radius"]))
        model.load_state_dict(state["modules"]["geometry"])
    except (KeyError, RuntimeError) as e:
        raise CheckpointError(f"{source} is not a NeTePu geometry checkpoint: {e}") from e
    model.eval()
    return model, config

