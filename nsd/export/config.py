"""The export's settings: ``conf/export.yaml`` loaded from Python, and their checks.

:func:`check_export_config` runs before any work and names the key that is out of range.
"""

from __future__ import annotations

from importlib.resources import files
from typing import Any

from omegaconf import DictConfig, OmegaConf

from nsd.core.errors import ConfigError
from nsd.inference.multiview import InferenceSettings

__all__ = ["check_export_config", "load_export_config"]


_CLI_ONLY = ("defaults", "hydra")


def load_export_config(**overrides: Any) -> DictConfig:
    """The shipped ``conf/export.yaml`` with top-level or dotted-key overrides.

    Example:
        >>> cfg = load_export_config(checkpoint="run", **{"crop.size": 32})
        >>> cfg.crop.size, cfg.batch_size
        (32, 8)
    """
    with (files("nsd.conf") / "export.yaml").open() as f:
        cfg = OmegaConf.load(f)
    with (files("nsd.conf") / "inference" / "default.yaml").open() as f:
        cfg.inference = OmegaConf.load(f)  # the defaults list's group, as nsd-export composes it
    for key in _CLI_ONLY:
        cfg.pop(key, None)
    for key, value in overrides.items():
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if not OmegaConf.is_dict(node) or leaf not in node.keys():
            raise ConfigError(f"export config has no key {key!r}")
        OmegaConf.update(cfg, key, value, merge=False)
    return cfg


def check_export_config(cfg: DictConfig) -> None:
    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise ConfigError(f"{key}: {what}, got {OmegaConf.select(cfg, key)!r}")

    need(
        OmegaConf.select(cfg, "checkpoint", throw_on_missing=False) not in (None, "???"),
        "checkpoint",
        "give the checkpoint.pt of nsd-train (checkpoint=...)",
    )
    need(int(cfg.batch_size) >= 1, "batch_size", "must be >= 1")
    need(0 < float(cfg.threshold) < 1, "threshold", "must be in (0, 1)")
    need(cfg.refine in ("residual", "none"), "refine", "must be residual or none")
    InferenceSettings.from_config(cfg.get("inference"))  # a clear error naming the key
    need(int(cfg.crop.size) >= 4, "crop.size", "must be >= 4 pixels")
    need(float(cfg.crop.margin) >= 0, "crop.margin", "must be >= 0")
    need(int(cfg.crop.chunk) >= 1, "crop.chunk", "must be >= 1")
    need(cfg.embeddings.format in ("parquet", "npz"), "embeddings.format", "parquet or npz")
    need(int(cfg.embeddings.row_group_size) >= 1, "embeddings.row_group_size", "must be >= 1")
    need(0 <= float(cfg.tracking.appearance_weight) <= 1, "tracking.appearance_weight", "in [0, 1]")
    need(int(cfg.tracking.max_gap) >= 0, "tracking.max_gap", "must be >= 0")
    need(int(cfg.views.max_points) >= 1, "views.max_points", "must be >= 1")
    need(int(cfg.views.thumbnail) >= 4, "views.thumbnail", "must be >= 4 pixels")
