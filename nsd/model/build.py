"""Building the Bi-NVS model (detector, encoder, decoder) from the ``model`` config group.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from nsd.core.errors import ConfigError
from nsd.model.bi_nvs import BiNVS, BiNVSConfig
from nsd.model.decoder import Decoder
from nsd.model.detector import Detector
from nsd.model.encoder import Encoder

__all__ = ["build_model"]


_BINVS_KEYS = {f for f in BiNVSConfig.__dataclass_fields__}


def build_model(model_cfg: Mapping[str, Any]) -> BiNVS:
    """BiNVS with its three networks from the ``model`` config group."""
    m = dict(model_cfg)
    cfg = BiNVSConfig(**{k: v for k, v in m.items() if k in _BINVS_KEYS})
    det = dict(m.get("detector", {}))
    det["widths"] = tuple(det.get("widths", (16, 32, 64, 64)))
    enc = dict(m.get("encoder", {}))
    enc["widths"] = tuple(enc.get("widths", (32, 64, 96, 128)))
    dec = dict(m.get("decoder", {}))
    dec["widths"] = tuple(dec.get("widths", (128, 64, 32)))
    for name, widths, size in (
        ("detector", det["widths"], det.get("input_size", 64)),
        ("encoder", enc["widths"], cfg.crop_size),
        ("decoder", dec["widths"], cfg.crop_size),
    ):
        if size % 2 ** len(widths):
            raise ConfigError(
                f"model.{name}: input size {size} must be divisible by 2^{len(widths)} "
                f"(one halving per width in {list(widths)})"
            )
    return BiNVS(
        cfg,
        Detector(num_windows=cfg.num_windows, **det),
        Encoder(
            crop_size=cfg.crop_size,
            app_dims=enc.pop("app_dims", 128),
            points=enc.pop("points", 200),
            **enc,
        ),
        Decoder(
            crop_size=cfg.crop_size,
            app_dims=model_cfg["encoder"].get("app_dims", 128),
            points=model_cfg["encoder"].get("points", 200),
            **dec,
        ),
    )
