"""The settings of a synthetic scene, checked: :class:`SceneConfig`.

Built from the Hydra config ``conf/synth.yaml`` (``nsd-synth``), from a plain
dict (:meth:`SceneConfig.from_dict`) or directly. Every bad value raises
:class:`~nsd.core.errors.ConfigError` naming its key. The config (with a generator
version) is hashed into :meth:`SceneConfig.hash`, which names cached scenes.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from importlib.resources import files
from typing import Any

from omegaconf import OmegaConf

from nsd.core.errors import ConfigError
from nsd.synth.backdrop import Backdrop
from nsd.synth.motion import MotionConfig
from nsd.synth.rigs import RIG_KINDS
from nsd.synth.shading import Light
from nsd.synth.skeleton import get_species

__all__ = [
    "CLI_KEYS",
    "GENERATOR_VERSION",
    "MAX_INDIVIDUALS",
    "PreviewConfig",
    "SceneConfig",
    "shipped_scene_values",
]

GENERATOR_VERSION = 1  # bump when the same config would render different pixels
MAX_INDIVIDUALS = 8


@dataclass(frozen=True)
class PreviewConfig:
    """The image grid ``gt/preview.png``.

    Attributes:
        cameras: number of cameras (rows), the first ones of the rig.
        frames: number of frames (columns), evenly spread.
        zoom: integer upscaling of each image.
    """

    cameras: int = 4
    frames: int = 4
    zoom: int = 2


CLI_KEYS = ("out", "overwrite", "defaults", "hydra")  # synth.yaml keys that are not scene settings


@functools.cache
def _shipped() -> dict[str, Any]:
    with (files("nsd.conf") / "synth.yaml").open() as f:
        values = OmegaConf.to_container(OmegaConf.load(f), resolve=True)
    return {k: v for k, v in values.items() if k not in CLI_KEYS}


def shipped_scene_values() -> dict[str, Any]:
    """``conf/synth.yaml``'s scene settings (a fresh copy): the default scene."""
    return copy.deepcopy(_shipped())


def _sub(cls, value: Any, key: str):
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise ConfigError(f"{key}: expected a mapping, got {value!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(value) - names)
    if unknown:
        raise ConfigError(f"{key}: unknown keys {unknown}; known: {sorted(names)}")
    try:
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in value.items()})
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{key}: {e}") from e


@dataclass(frozen=True)
class SceneConfig:
    """Everything that defines a synthetic scene (``datasets/synthetic.md``).

    Attributes:
        seed: the single source of randomness (proportions, textures, motion).
        num_frames: frames T.
        fps: frames per second (motion speed and video rate).
        image_size: (width, height) in pixels.
        num_individuals: N in 1..8.
        species: species names, cycled over the individuals.
        texture_ids: one texture id per individual, or None: distinct ids from
            the pool, drawn with the seed, never a look-alike pair.
        proportion_variation: spread of body proportions (0: the mean body).
        rig: ``kind`` (corners, ring, nepumoo), ``distortion`` (OpenCV
            coefficients or None) and the rig builder's keyword arguments
            (:mod:`nsd.synth.rigs`).
        motion: :class:`~nsd.synth.motion.MotionConfig`.
        backdrop: :class:`~nsd.synth.backdrop.Backdrop` (wall, tiles, its own noise seed).
        light: :class:`~nsd.synth.shading.Light`.
        supersample: odd samples per pixel side for the RGB images (1: off).
        video: write ``<cam>.mp4`` (lossy) instead of PNG folders.
        dense: write the per camera-frame dense maps ``gt/dense/``.
        preview: :class:`PreviewConfig`.
    """

    seed: int
    num_frames: int
    fps: float
    image_size: tuple[int, int]
    num_individuals: int
    species: tuple[str, ...]
    texture_ids: tuple[int, ...] | None
    proportion_variation: float
    rig: dict
    motion: MotionConfig
    backdrop: Backdrop
    light: Light
    supersample: int
    video: bool
    dense: bool
    preview: PreviewConfig

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the first bad key."""

        def is_int(x) -> bool:
            return isinstance(x, int) and not isinstance(x, bool)

        if not is_int(self.seed):
            raise ConfigError(f"seed: must be an integer, got {self.seed!r}")
        if not is_int(self.num_individuals) or not 1 <= self.num_individuals <= MAX_INDIVIDUALS:
            raise ConfigError(
                f"num_individuals: must be an integer in 1..{MAX_INDIVIDUALS}, "
                f"got {self.num_individuals!r}"
            )
        if not is_int(self.num_frames) or self.num_frames < 1:
            raise ConfigError(f"num_frames: must be an integer >= 1, got {self.num_frames!r}")
        if not isinstance(self.fps, (int, float)) or not self.fps > 0:
            raise ConfigError(f"fps: must be > 0, got {self.fps!r}")
        size = tuple(self.image_size)
        if len(size) != 2 or not all(is_int(s) and s > 0 for s in size):
            raise ConfigError(
                "image_size: must be two positive integers [width, height], "
                f"got {self.image_size!r}"
            )
        if isinstance(self.species, str) or not self.species:
            raise ConfigError(f"species: must be a non-empty list of names, got {self.species!r}")
        for s in self.species:
            get_species(s, key="species")
        if self.texture_ids is not None:
            ids = tuple(self.texture_ids)
            if len(ids) != self.num_individuals or not all(is_int(i) and i >= 0 for i in ids):
                raise ConfigError(
                    f"texture_ids: must be null or {self.num_individuals} integers >= 0 "
                    f"(one per individual), got {self.texture_ids!r}"
                )
        if not isinstance(self.proportion_variation, (int, float)) or self.proportion_variation < 0:
            raise ConfigError(
                f"proportion_variation: must be >= 0, got {self.proportion_variation!r}"
            )
        if not isinstance(self.rig, Mapping) or self.rig.get("kind") not in RIG_KINDS:
            kind = self.rig.get("kind") if isinstance(self.rig, Mapping) else self.rig
            raise ConfigError(f"rig.kind: unknown rig {kind!r}; choose one of {list(RIG_KINDS)}")
        dist = self.rig.get("distortion")
        if dist is not None and len(dist) not in (4, 5, 8):
            raise ConfigError(
                f"rig.distortion: null or 4, 5 or 8 OpenCV coefficients, got {dist!r}"
            )
        self.motion.validate()
        if not 0.0 <= self.light.ambient <= 1.0:
            raise ConfigError(f"light.ambient: must be in [0, 1], got {self.light.ambient}")
        if len(tuple(self.light.direction)) != 3:
            raise ConfigError(f"light.direction: must be 3 numbers, got {self.light.direction}")
        if not self.backdrop.wall_radius > 0 or not self.backdrop.wall_height > 0:
            raise ConfigError("backdrop.wall_radius and backdrop.wall_height: must be > 0")
        if self.backdrop.wall_radius <= self.motion.area_radius + 2.0:
            raise ConfigError(
                f"backdrop.wall_radius: {self.backdrop.wall_radius} m must exceed "
                f"motion.area_radius + 2 m ({self.motion.area_radius + 2.0} m)"
            )
        if not is_int(self.supersample) or self.supersample < 1 or self.supersample % 2 == 0:
            raise ConfigError(f"supersample: must be an odd integer >= 1, got {self.supersample!r}")
        p = self.preview
        if not all(is_int(x) and x >= 1 for x in (p.cameras, p.frames, p.zoom)):
            raise ConfigError(f"preview: cameras, frames and zoom must be integers >= 1, got {p}")

    # ------------------------------------------------------------------ conversions
    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> SceneConfig:
        """Build from a plain (e.g. Hydra) mapping; unknown keys raise :class:`ConfigError`.

        Keys the mapping lacks take ``conf/synth.yaml``'s values (the only source of
        defaults), also inside ``motion``, ``backdrop``, ``light`` and ``preview``; a
        given ``rig`` replaces the shipped one whole (its keys depend on its kind).
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(f"unknown scene config keys {unknown}; known: {sorted(names)}")
        shipped = shipped_scene_values()
        kw: dict[str, Any] = {**shipped, **dict(values)}
        for key in ("motion", "backdrop", "light", "preview"):
            given = values.get(key)
            if isinstance(given, Mapping):
                kw[key] = {**shipped[key], **given}
        for key in ("image_size", "species", "texture_ids"):
            if key in kw and kw[key] is not None and not isinstance(kw[key], str):
                try:
                    kw[key] = tuple(kw[key])
                except TypeError:
                    raise ConfigError(f"{key}: expected a list, got {kw[key]!r}") from None
        if isinstance(kw.get("species"), str):
            kw["species"] = (kw["species"],)
        if "rig" in kw:
            if not isinstance(kw["rig"], Mapping):
                raise ConfigError(f"rig: expected a mapping with 'kind', got {kw['rig']!r}")
            kw["rig"] = dict(kw["rig"])
        sub = {
            "motion": MotionConfig,
            "backdrop": Backdrop,
            "light": Light,
            "preview": PreviewConfig,
        }
        for key, typ in sub.items():
            if key in kw:
                kw[key] = _sub(typ, kw[key], key)
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values (the inverse of :meth:`from_dict`)."""

        def plain(x):
            if dataclasses.is_dataclass(x):
                return {f.name: plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
            if isinstance(x, Mapping):
                return {k: plain(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [plain(v) for v in x]
            return x

        return plain(self)

    def hash(self) -> str:
        """12 hex digits identifying the rendered content (config + generator version)."""
        blob = json.dumps({"v": GENERATOR_VERSION, "config": self.to_dict()}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:12]

    def replace(self, **changes: Any) -> SceneConfig:
        """A copy with some fields changed (sub-configs may be given as dicts)."""
        return SceneConfig.from_dict({**self.to_dict(), **changes})

    @property
    def species_of_individuals(self) -> list[str]:
        return [self.species[i % len(self.species)] for i in range(self.num_individuals)]
