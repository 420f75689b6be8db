r"""The texture model's settings (:class:`TextureConfig`), read from ``conf/netepu/texture``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from netepu.texture.embedding import COLOUR_STATISTICS
from nsd.core.errors import ConfigError

__all__ = ["TextureConfig"]


# ----------------------------------------------------------------------------- config
@dataclass
class TextureConfig:
    """The ``netepu.texture.model`` config (every field commented in the YAML file)."""

    latent: int = 128
    features: int = 64
    use_nnopcs: bool = True
    use_normals: bool = False
    local_features: bool = True
    crop_size: int = 64
    crop_margin: float = 0.1
    widths: list[int] = field(default_factory=lambda: [16, 32, 64, 128])
    blocks_per_stage: int = 2
    dense_hidden: int = 256
    decoder_hidden: int = 256
    renderer: dict[str, Any] = field(default_factory=dict)
    reid_colour: bool = False

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> TextureConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - names)
        if unknown:
            raise ConfigError(
                f"netepu.texture.model: unknown keys {unknown}; known {sorted(names)}"
            )
        c = cls(**dict(cfg))
        if c.crop_size < 16 or c.latent < 1 or c.features < 1 or c.crop_margin < 0:
            raise ConfigError(
                "netepu.texture.model: crop_size >= 16, latent and features >= 1, crop_margin >= 0"
            )
        if c.use_normals and not c.use_nnopcs:
            raise ConfigError(
                "netepu.texture.model.use_normals needs use_nnopcs: the normals come from the "
                "geometry model's depth, rendered with the NNOPCS map (an RGB-only model: "
                "use_nnopcs=false use_normals=false)"
            )
        return c

    @property
    def reid_dims(self) -> int:
        """Length of the re-identification input: d_z [+ the colour statistics]."""

        return self.latent + (COLOUR_STATISTICS if self.reid_colour else 0)

    @property
    def surface_channels(self) -> int:
        """Channels of the rendered surface crop: NNOPCS (3) [+ world normals (3)]."""
        return (3 if self.use_nnopcs else 0) + (3 if self.use_normals else 0)
