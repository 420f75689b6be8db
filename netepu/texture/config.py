r"""The texture model's settings (:class:`TextureConfig`), read from ``conf/netepu/texture``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from netepu.texture.embedding import COLOUR_STATISTICS
from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError

__all__ = ["TextureConfig"]


# ----------------------------------------------------------------------------- config
@dataclass
class TextureConfig(ConfigSection):
    """The ``netepu.texture.model`` config (every field commented in the YAML file)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml (netepu/texture)
    KEY: ClassVar[str] = "netepu.texture.model"

    latent: int
    features: int
    use_nnopcs: bool
    use_normals: bool
    local_features: bool
    renderer_geometry: bool
    crop_size: int
    crop_margin: float | None
    widths: list[int]
    blocks_per_stage: int
    dense_hidden: int
    decoder_hidden: int
    renderer: dict[str, Any]
    reid_colour: bool

    def validate(self) -> None:
        """Ranges and combinations (:meth:`from_config` and :meth:`defaults` call it)."""
        c = self
        margin_ok = c.crop_margin is None or (
            isinstance(c.crop_margin, (int, float)) and not isinstance(c.crop_margin, bool)
            and c.crop_margin >= 0
        )
        if c.crop_size < 16 or c.latent < 1 or c.features < 1 or not margin_ok:
            raise ConfigError(
                "netepu.texture.model: crop_size >= 16, latent and features >= 1, crop_margin "
                f">= 0 or null (the whole frame); got crop_size={c.crop_size!r}, "
                f"latent={c.latent!r}, features={c.features!r}, crop_margin={c.crop_margin!r}"
            )
        if c.use_normals and not c.use_nnopcs:
            raise ConfigError(
                "netepu.texture.model.use_normals needs use_nnopcs: the normals come from the "
                "geometry model's depth, rendered with the NNOPCS map (an RGB-only model: "
                "use_nnopcs=false use_normals=false)"
            )

    @property
    def reid_dims(self) -> int:
        """Length of the re-identification input: d_z [+ the colour statistics]."""

        return self.latent + (COLOUR_STATISTICS if self.reid_colour else 0)

    @property
    def surface_channels(self) -> int:
        """Channels of the rendered surface crop: NNOPCS (3) [+ world normals (3)]."""
        return (3 if self.use_nnopcs else 0) + (3 if self.use_normals else 0)
