"""Building the Bi-NVS model (detector, encoder, decoder) from the ``model`` config group.

The convolutions' weights are stored channels-last (NHWC), the layout oneDNN computes in on a
CPU: without it every convolution reorders its input and weights, and a default training step
is ~5 % slower on one thread and on two (``docs/benchmarks/threads.md``). The layout changes
no value the model computes beyond rounding, and checkpoints load into either layout.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from nsd.core.errors import ConfigError
from nsd.model.bi_nvs import BiNVS, BiNVSConfig
from nsd.model.decoder import Decoder
from nsd.model.detector import Detector
from nsd.model.encoder import Encoder
from nsd.model.mask_refiner import MaskRefiner

__all__ = ["build_model"]


def build_model(model_cfg: Mapping[str, Any]) -> BiNVS:
    """BiNVS with its three networks, and the mask refiner where ``mask_refiner.widths`` is not
    empty, from the ``model`` config group (a config without ``mask_refiner``, as in
    checkpoints written before it existed, has none)."""
    m = dict(model_cfg)
    cfg = BiNVSConfig.from_config(m)
    if cfg.num_windows == "auto":
        raise ConfigError("model.num_windows=auto is chosen for a scene when training starts "
                          "(nsd.training.window_count); give a number to build a model alone")
    det, enc, dec = _section(m, "detector"), _section(m, "encoder"), _section(m, "decoder")
    for name, widths, size in (
        ("detector", det["widths"], det["input_size"]),
        ("encoder", enc["widths"], cfg.crop_size),
        ("decoder", dec["widths"], cfg.crop_size),
    ):
        if size % 2 ** len(widths):
            raise ConfigError(
                f"model.{name}: input size {size} must be divisible by 2^{len(widths)} "
                f"(one halving per width in {list(widths)})"
            )
    model = BiNVS(
        cfg,
        Detector(num_windows=cfg.num_windows, **det),
        Encoder(
            crop_size=cfg.crop_size,
            app_dims=enc.pop("app_dims"),
            points=enc.pop("points"),
            **enc,
        ),
        Decoder(
            crop_size=cfg.crop_size,
            app_dims=model_cfg["encoder"]["app_dims"],
            points=model_cfg["encoder"]["points"],
            **dec,
        ),
        _refiner(m),
    )
    return model.to(memory_format=torch.channels_last)


def _refiner(model_cfg: dict[str, Any]) -> MaskRefiner | None:
    """The mask refiner of ``model.mask_refiner`` (None: no section, or no widths; a section
    without ``grow`` has no bound, as the refiner's first runs)."""
    sec = model_cfg.get("mask_refiner") or {}
    widths = tuple(sec.get("widths") or ())
    if any(int(w) < 1 for w in widths):
        raise ConfigError(
            f"model.mask_refiner.widths must be positive channel counts, got {list(widths)}")
    grow = sec.get("grow")
    if grow is not None and not (isinstance(grow, (int, float)) and grow > 0):
        raise ConfigError(f"model.mask_refiner.grow must be a number > 0 or null, got {grow!r}")
    return MaskRefiner(tuple(int(w) for w in widths), grow) if widths else None


def _section(model_cfg: dict[str, Any], name: str) -> dict[str, Any]:
    """A network's sub-section of the ``model`` config, its ``widths`` as a tuple."""
    if name not in model_cfg:
        raise ConfigError(f"model.{name}: missing (defaults: conf/model/nsd.yaml)")
    sec = dict(model_cfg[name])
    if "widths" not in sec:
        raise ConfigError(f"model.{name}.widths: missing (defaults: conf/model/nsd.yaml)")
    sec["widths"] = tuple(sec["widths"])
    return sec
