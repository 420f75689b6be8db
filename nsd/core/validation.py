"""Every config value checked before any work: types, ranges, finiteness, choices.

A value's type and sign come from its shipped default (``conf/``, the one source of
defaults): a key whose default is an integer must stay an integer, a float a finite number,
a boolean a boolean, a string a string, and a number whose default is >= 0 may not turn
negative. :data:`RULES` says more where a key needs it (a size >= 1, a fraction <= 1, one
of a few words, a value that may be negative). Rules are grouped by config group, one
table each, keyed by the path inside the group.

:func:`check_config` runs on the composed config of an app and raises a
:class:`~nsd.core.errors.ConfigError` naming the key, the value and the allowed range.

Example:
    >>> from nsd.core.config import compose_app
    >>> check_config("train", compose_app("train", ["batch_size=-1"]))
    Traceback (most recent call last):
    ...
    nsd.core.errors.ConfigError: batch_size = -1: must be an integer >= 1
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from nsd.core.config import compose_app
from nsd.core.device import DEVICE_PATTERN
from nsd.core.errors import ConfigError

__all__ = ["RULES", "Rule", "check_config", "leaves"]

_ANY = object()


@dataclass(frozen=True)
class Rule:
    """What a config value may be.

    Attributes:
        kind: int | number | bool | str | ints | numbers | strs (a list of words) | any.
        low, high: inclusive bounds of a number (or of each element of a list); None: open.
        above: exclusive lower bound (a rate > 0).
        choices: allowed words (kinds str and strs).
        null: None is allowed.
        length: exact list length.
        odd: an odd integer.
        allow: extra values allowed besides the kind (e.g. ``auto`` for a boolean).
        pattern: a regular expression a string must match (kind str), said as ``words``.
    """

    kind: str
    low: float | None = None
    high: float | None = None
    above: float | None = None
    choices: tuple[str, ...] = ()
    null: bool = False
    length: int | None = None
    odd: bool = False
    allow: tuple[Any, ...] = ()
    pattern: re.Pattern[str] | None = None
    words: str = ""  # how a pattern's values are said to a user

    def describe(self) -> str:
        """The allowed range in words, e.g. ``an integer >= 1``."""
        if self.kind == "str" and self.choices:
            words = "one of " + ", ".join(self.choices)
        elif self.kind == "str" and self.pattern is not None:
            words = self.words or "a string matching " + self.pattern.pattern
        elif self.kind == "strs":
            words = "a list of any of " + ", ".join(self.choices)
        else:
            noun = {"int": "an integer", "number": "a finite number", "bool": "true or false",
                    "str": "a string", "ints": "a list of integers",
                    "numbers": "a list of finite numbers", "any": "any value"}[self.kind]
            if self.length is not None:
                noun = noun.replace("a list of", f"a list of {self.length}")
            words = noun + self._bounds()
            if self.odd:
                words += ", odd"
        if self.allow:
            words += " or " + " or ".join(str(a) for a in self.allow)
        return words + (" or null" if self.null else "")

    def _bounds(self) -> str:
        each = " each" if self.kind in ("ints", "numbers") else ""
        parts = []
        if self.above is not None:
            parts.append(f"> {self.above:g}")
        if self.low is not None:
            parts.append(f">= {self.low:g}")
        if self.high is not None:
            parts.append(f"<= {self.high:g}")
        return (each + " " + " and ".join(parts)) if parts else ""

    def ok(self, value: Any) -> bool:
        """Whether ``value`` (a plain Python value) satisfies the rule."""
        if self.kind == "any":
            return True
        if value is None:
            return self.null
        if any(value == a and type(value) is type(a) for a in self.allow):
            return True
        if self.kind in ("ints", "numbers"):
            if not isinstance(value, (list, tuple)):
                return False
            if self.length is not None and len(value) != self.length:
                return False
            scalar = Rule("int" if self.kind == "ints" else "number", self.low, self.high,
                          self.above)
            return all(scalar.ok(v) for v in value)
        if self.kind == "strs":
            return isinstance(value, (list, tuple)) and all(
                isinstance(v, str) and v in self.choices for v in value)
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "str":
            return (isinstance(value, str) and (not self.choices or value in self.choices)
                    and (self.pattern is None or bool(self.pattern.match(value))))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.kind == "int" and not isinstance(value, int):
            return False
        if not math.isfinite(value):
            return False
        if self.odd and value % 2 != 1:
            return False
        return ((self.low is None or value >= self.low)
                and (self.high is None or value <= self.high)
                and (self.above is None or value > self.above))


def _r(kind: str, *a: Any, **kw: Any) -> Rule:
    return Rule(kind, *a, **kw)


POS = _r("int", low=1)  # a count or size
RATE = _r("number", above=0)  # a learning rate or physical scale
FRACTION = _r("number", low=0, high=1)
SIGNED = _r("number")
NATS = _r("number", allow=(math.inf, -math.inf))  # a log-likelihood margin, or never / always
SIZE2 = _r("ints", low=1, length=2)  # [width, height]
VEC3 = _r("numbers", length=3)
WIDTHS = _r("ints", low=1)
NULL_TEXT = _r("str", null=True)  # a path, a name or null
UNITS = _r("str", choices=("auto", "m", "cm", "mm"))  # nsd.cameras.units.UNITS and auto
ALWAYS = _r("any")
BACKGROUND = _r("str", choices=("median", "modes"))  # nsd.cues.background.BACKGROUND_METHODS
DEVICE = _r("str", pattern=DEVICE_PATTERN, words="one of auto, cpu, cuda, cuda:N, mps")

# Per config group (conf/<group>/*.yaml, or the app's own top-level keys): the rules that
# the shipped default does not imply. Keys are paths inside the group.
RULES: dict[str, dict[str, Rule]] = {
    "data": {"image_size": SIZE2, "val_fraction": _r("number", low=0, high=0.99),
             "cameras": _r("any"), "scene": NULL_TEXT, "same_view": FRACTION, "units": UNITS,
             "frame_stride": POS, "background": BACKGROUND},
    "model": {
        "num_windows": _r("int", low=1, allow=("auto",)), "crop_size": _r("int", low=4), "mode": _r(
            "str", choices=("bi_nvs", "autoencoder")),
        "association_dims": POS, "association_unit": RATE, "mask_floor": RATE,
        "mask_pool": _r("int", low=1, odd=True), "mask_normalisation": _r(
            "str", choices=("visible", "max")),
        "crop_padding": _r("str", choices=("zeros", "border", "reflection")),
        "presence_gate": _r("str", choices=("soft", "hard", "none")),
        "detector.input_size": _r("int", low=16), "detector.widths": WIDTHS,
        "detector.hidden": POS, "detector.min_scale": _r("number", above=0, high=1),
        "detector.max_scale": _r("number", above=0, high=2), "detector.border": FRACTION,
        "detector.presence_init": _r("number", above=0, high=1),
        "detector.head": _r("str", choices=("mlp", "attention")),
        "encoder.widths": WIDTHS, "encoder.app_dims": POS, "encoder.points": POS,
        "decoder.widths": WIDTHS, "decoder.dropout": _r("number", low=0, high=0.99),
        "decoder.convs": POS, "mask_refiner.widths": WIDTHS,
        "mask_refiner.grow": _r("number", above=0, null=True),
    },
    "loss": {"ssim_window": _r("int", low=3, odd=True), "evidence_softness": RATE},
    "prior_presence": {
        "target": _r("str", choices=("none", "marginal", "hull")),
        "normalise": _r("str", choices=("mask", "box")),
        "cap": _r("str", choices=("none", "proposals")),
        "gate": _r("str", choices=("soft", "hard", "none")),
        "count_window": _r("int", low=1, odd=True),
        "count_population": _r("str", choices=("frame", "scene")),
    },
    "prior_proposal": {"source": _r("str", choices=("multiview", "single_view", "none")),
                       "resolution": _r("int", low=8), "split": _r("bool", allow=("auto",)),
                       "min_views": _r("int", low=2, allow=("auto",))},
    "prior_depth": {"source": _r("str", choices=("proposals", "triangulation", "none")),
                    "unit": RATE},
    "prior_association": {"score": _r("str", choices=("appearance", "full"))},
    "prior_scale": {"target": _r("number", above=0, high=2)},
    "prior_aspect": {"ratio": RATE},
    "optim": {"lr_detector": RATE, "lr_encoder": RATE, "lr_decoder": RATE},
    "trainer": {"max_steps": _r("int"), "max_minutes": SIGNED, "eval_at_minutes": _r(
        "numbers", low=0)},
    "inference": {"views": _r("str", choices=("multiview", "single")),
                  "window_blend": FRACTION, "depth": _r("str", choices=("hull", "detector")),
                  "resolution": _r("int", low=8), "min_views": _r("int", low=2, allow=("auto",)),
                  # nats per voxel; inf: never, -inf: always (nsd.cues.clustering.MixtureRules)
                  "mixture_gain": NATS, "mixture_slack": NATS, "mixture_scene_gain": NATS,
                  "mixture_scene_sample": POS,
                  # the individuals' colour models (nsd.inference.colour_models); 0: off
                  "colour_model": _r("number", low=0), "colour_model_bins": _r(
                      "int", low=2, high=32), "colour_model_margin": _r("number", low=0),
                  "colour_model_separation": FRACTION,  # a kappa; 0: everywhere
                  "hole_share": FRACTION,  # of a mask's area (nsd.cues.holes); 0: off
                  "island_share": FRACTION,  # of a mask's area (nsd.cues.holes); 0: off
                  # the Potts term of nsd.inference.neighbours; weight 0: off
                  "neighbour_weight": _r("number", low=0), "neighbour_sigma": _r("number", low=0)},
    "train": {  # conf/train.yaml's own keys
        "device": DEVICE,
        "stage": _r("str", choices=("decomposition", "pose")), "batch_size": POS,
        "eval_frames": POS, "init_from": NULL_TEXT, "pose.label_fraction": _r(
            "number", above=0, high=1), "pose.hidden": POS,
        "pose.dropout": _r("number", low=0, high=0.99), "pose.lr": RATE, "pose.labels": NULL_TEXT,
    },
    "run": {"device": DEVICE,
        "scene": NULL_TEXT, "out": NULL_TEXT, "checkpoint": NULL_TEXT,
        "evaluate.frames": ALWAYS, "evaluate.refine": _r("str", choices=("residual", "none")),
        "netepu.geometry": NULL_TEXT, "netepu.texture": NULL_TEXT,
        # netepu.pipeline.species_models.SPECIES (a test keeps them equal)
        "netepu.species": _r("str", choices=("auto", "biped", "quadruped", "mixed")),
        "netepu.keypoints.frame_step": POS, "netepu.keypoints.min_views": _r("int", low=2),
        "netepu.keypoints.steps": POS, "netepu.keypoints.templates": POS,
        "netepu.keypoints.workers": _r("int", low=1, allow=("auto",)),
        "netepu.keypoints.warm_steps": _r("int", low=0),
        "netepu.keypoints.point_budget": _r("int", low=0),
        "netepu.keypoints.initialiser": NULL_TEXT, "netepu.keypoints.init_steps": POS,
        "netepu.keypoints.init_templates": _r("int", low=0, allow=("auto",)),
        "netepu.keypoints.init_poses": _r("int", low=0),
        "netepu.keypoints.init_points_per_view": POS,
        "netepu.keypoints.smooth_frames": _r("number", low=0),
        "netepu.keypoints.species_steps": _r("int", low=0),
        "netepu.keypoints.travel_speed": _r("number", low=0, allow=("auto",)),
        "netepu.keypoints.heading_tolerance": _r("number", low=0, allow=("auto",)),
        "netepu.keypoints.source": _r("str", choices=("inverse", "regressor")),
        "netepu.keypoints.label_fraction": _r("number", above=0, high=1),
        "netepu.keypoints.regressor_steps": POS, "netepu.keypoints.labels": NULL_TEXT,
        "netepu.identities.method": _r("str", choices=("auto", "subjects", "rows", "tracks",
                                                        "motion")),
        "netepu.identities.jump": _r("number", above=0, allow=("auto",)),
        "netepu.identities.restarts": POS,
        "netepu.identities.fill": _r("str", choices=("app", "nearest", "tracks")),
        "grids.size": _r("int", low=16),
        "overlays.size": _r("int", low=16), "overlays.fps": RATE,
        "quality.max_frames": _r("int", low=0), "quality.worst": _r("int", low=0),
        "formats.which": _r("strs", choices=("slp", "nwb", "dlc", "trc", "c3d")),
        "formats.fps": _r("number", above=0, null=True),
    },
    "eval": {"device": DEVICE, "checkpoint": _r("str"), "scene": NULL_TEXT, "frames": ALWAYS,
             "out": NULL_TEXT, "export": NULL_TEXT, "labels": NULL_TEXT, "identities": NULL_TEXT,
             "refine": _r("str", choices=("residual", "none"))},
    "export": {"device": DEVICE,
        "checkpoint": _r("str"), "scene": NULL_TEXT, "out": NULL_TEXT, "cameras": ALWAYS,
        "frames": ALWAYS, "batch_size": POS, "threshold": _r("number", above=0, high=0.999),
        "refine": _r("str", choices=("residual", "none")),
        "native_refine": _r("bool", allow=("auto",)),
        "native_colour": _r("bool"), "workers": _r("int", low=1, allow=("auto",)),
        "crop.size": _r("int", low=8), "crop.chunk": POS,
        "embeddings.format": _r("str", choices=("parquet", "npz")),
        "embeddings.row_group_size": POS, "tracking.appearance_weight": FRACTION,
        "tracking.min_similarity": FRACTION, "tracking.position_weight": FRACTION,
        "tracking.max_tracks": _r("int", low=1, null=True, allow=("auto",)),
        "tracking.position_scale": _r("number", above=0, allow=("auto",)), "views.max_points": POS,
        "views.thumbnail": _r("int", low=4), "views.perplexity": RATE,
    },
    "synth": {
        "out": NULL_TEXT, "num_frames": POS, "fps": RATE, "image_size": SIZE2,
        "num_individuals": _r("int", low=1, high=8), "species": _r("any"),
        "texture_ids": _r("ints", low=0, null=True), "supersample": _r("int", low=1, odd=True),
        "rig.kind": _r("str", choices=("corners", "ring", "nepumoo")), "rig.count": POS,
        "rig.half_width": RATE, "rig.fov_deg": _r("number", above=0, high=179),
        "rig.target": VEC3, "rig.distortion": _r("numbers", null=True),
        "rig.height": SIGNED, "motion.interaction": _r("str", choices=("free", "close", "huddle")),
        "motion.linger": FRACTION,
        "motion.area_radius": RATE, "backdrop.wall_radius": RATE, "backdrop.tile": RATE,
        "light.direction": VEC3, "light.ambient": FRACTION, "preview.zoom": POS,
    },
    "netepu_train": {"device": DEVICE, "stage": _r("str", choices=("geometry", "texture")),
                     "init_from": NULL_TEXT, "objective": _r("str")},
    "netepu": {  # netepu-train's netepu.* (conf/netepu/...)
        "optim.batch_size": POS, "optim.lr": RATE, "optim.lr_decay": _r(
            "number", above=0, high=1),
        "render.mode": _r("str", choices=("dense", "culled", "coarse_to_fine")),
        "render.chunk": POS, "eval.eval_views": POS,
        "model.renderer.vca_mode": _r("str", choices=("factorised", "reference")),
        "texture.model.renderer.vca_mode": _r("str", choices=("factorised", "reference")),
        "data.species": _r("str", choices=("biped", "quadruped")), "data.radius": RATE,
        "data.image_size": SIZE2, "data.cache_dir": NULL_TEXT, "data.n_keypoints": _r(
            "int", low=1, null=True),
        "data.margin": ALWAYS, "texture.data.cache_dir": NULL_TEXT,
        "texture.optim.lr": RATE, "texture.optim.batch_size": POS,
        "texture.model.crop_size": _r("int", low=8), "texture.model.widths": WIDTHS,
        "texture.model.crop_margin": _r("number", low=0, null=True),  # null: the whole frame
        "texture.optim.contrast_temperature": RATE,
    },
    "check": {"scene": NULL_TEXT, "cameras": ALWAYS, "units": UNITS, "background": BACKGROUND},
    "calib": {"calibration": _r("str"), "units": UNITS, "convert": NULL_TEXT, "preview": NULL_TEXT,
              "format": _r("str", choices=("auto", "anipose", "caliscope", "opencv", "panoptic",
                                           "colmap", "colmap_bin", "dlt"))},
    "netepu_embed": {"device": DEVICE, "export": _r("str"), "checkpoint": _r("str"),
                     "keypoints": NULL_TEXT, "calibration": NULL_TEXT, "maps": NULL_TEXT,
                     "batch_size": POS,
                     "column": _r("str")},
}

# Which table checks a top-level key of an app: the app's own table unless the key is a
# config group (or, for nsd-run, another app's whole config).
_GROUPS = {
    "train": ("data", "model", "loss", "optim", "trainer", "inference", "prior_position",
              "prior_scale", "prior_aspect", "prior_presence", "prior_proposal",
              "prior_depth", "prior_association", "prior_mask"),
    "eval": ("inference",), "export": ("inference",), "netepu_train": ("trainer", "netepu"),
}
_NESTED_APPS = {"run": {"train": "train", "export": "export"}}


def leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted path, plain value)`` of every leaf of a config (``hydra`` excluded); a list of
    mappings is one leaf."""
    if isinstance(node, DictConfig):
        for key in node.keys():
            if key == "hydra":
                continue
            child = node._get_node(key)
            path = f"{prefix}{key}"
            if isinstance(child, DictConfig) and not child._is_none():
                yield from leaves(child, path + ".")
            else:
                try:
                    value = OmegaConf.to_container(child, resolve=True) if isinstance(
                        child, ListConfig) else node[key]
                except Exception:  # an interpolation that cannot resolve: shown as written
                    value = child._value()
                yield path, value


def _inferred(default: Any) -> Rule:
    """The rule a shipped default implies: its type, and >= 0 when it is >= 0."""
    if default is None or default is _ANY:
        return ALWAYS
    if isinstance(default, bool):
        return _r("bool")
    if isinstance(default, int):
        return _r("int", low=0 if default >= 0 else None)
    if isinstance(default, float):
        return _r("number", low=0 if default >= 0 else None)
    if isinstance(default, str):
        return _r("str")
    if isinstance(default, list) and default and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in default):
        ints = all(isinstance(v, int) for v in default)
        return _r("ints" if ints else "numbers", low=0 if min(default) >= 0 else None)
    return ALWAYS


def _rule(app: str, path: str, default: Any) -> Rule:
    head, _, rest = path.partition(".")
    if rest and head in _GROUPS.get(app, ()):
        table, key = RULES.get(head, {}), rest
    else:
        table, key = RULES.get(app, {}), path
    return table.get(key) or _inferred(default)


@functools.cache
def _base(app: str) -> DictConfig:
    return compose_app(app)


def _defaults(app: str, overrides: Sequence[str]) -> dict[str, Any]:
    """The shipped default of every leaf, with the group choices among ``overrides``."""
    base = _base(app)
    groups = []
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        node = OmegaConf.select(base, key.split("@")[0], default=_ANY)
        if "=" in o and (node is _ANY or isinstance(node, DictConfig) or "@" in key):
            groups.append(o)  # a group choice (model=..., +preset=fast) or an added key
    return dict(leaves(compose_app(app, groups))) if groups else _base_leaves(app)


@functools.cache
def _base_leaves(app: str) -> dict[str, Any]:
    return dict(leaves(_base(app)))


def check_config(app: str, cfg: DictConfig, overrides: Sequence[str] = (),
                 prefix: str = "") -> None:
    """Check every value of ``cfg``, the composed config of ``app`` (``conf/<app>.yaml``).

    Args:
        app: the app's config name (train, run, eval, export, synth, netepu_train, ...).
        cfg: its composed config.
        overrides: the command line's overrides (their group choices select the defaults).
        prefix: prepended to key names in messages (``train.`` inside nsd-run).

    Raises:
        ConfigError: ``<key> = <value>: must be <range>``; the first bad value found.
    """
    nested = _NESTED_APPS.get(app, {})
    defaults = _defaults(app, overrides)
    groups = {k.rsplit(".", i)[0] for k in defaults for i in range(1, k.count(".") + 1)}
    for path, value in leaves(cfg):
        head = path.split(".", 1)[0]
        if head in nested:
            continue
        if path in groups:  # a value where the config holds a group of settings
            name = path.rsplit(".", 1)[-1]
            raise ConfigError(
                f"{prefix}{path} = {value!r}: {prefix}{path} is a group of settings, not one "
                f"value; choose its option with {name}@{prefix}{path}={value}, or set one of "
                f"its keys ({prefix}{path}.<key>=...)")
        rule = _rule(app, path, defaults.get(path, _ANY))
        if not rule.ok(value):
            raise ConfigError(f"{prefix}{path} = {value!r}: must be {rule.describe()}")
    for key, sub_app in nested.items():
        node = cfg.get(key)
        if not node:
            continue
        sub_overrides = [_nested_override(o, key) for o in overrides]
        sub_overrides = [o for o in sub_overrides if o]
        sub = node
        if sub_app == "export":  # nsd-run's export: {} holds overrides of nsd-export's config
            base = _base(sub_app)
            known = _base_leaves(sub_app)
            for path, _ in leaves(node):
                if path not in known:
                    raise ConfigError(f"{prefix}{key}.{path}: nsd-export has no such key "
                                      f"(conf/{sub_app}.yaml)")
            sub, sub_overrides = OmegaConf.merge(base, node), []
        check_config(sub_app, sub, sub_overrides, prefix=f"{prefix}{key}.")
    _check_relations(app, cfg, prefix)


def _nested_override(override: str, key: str) -> str:
    """``train.x=1`` -> ``x=1`` and ``model@train.model=m`` -> ``model=m`` for ``key`` train."""
    name, eq, value = override.partition("=")
    sign = name[: len(name) - len(name.lstrip("+~"))]
    name = name.lstrip("+~")
    if name.startswith(key + "."):
        return sign + name[len(key) + 1:] + eq + value
    group, at, package = name.partition("@")
    if at and package.startswith(key + "."):
        return sign + group + eq + value
    return ""


def _check_relations(app: str, cfg: DictConfig, prefix: str) -> None:
    """Rules between keys."""
    if app == "train":
        det = cfg.model.detector
        if det.min_scale > det.max_scale:
            raise ConfigError(
                f"{prefix}model.detector.min_scale = {det.min_scale} is above "
                f"model.detector.max_scale = {det.max_scale}")
