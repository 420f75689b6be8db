"""The one source of defaults: the shipped YAML configs (``conf/``, installed as ``nsd.conf``).

Every settings dataclass of the toolkit is a :class:`ConfigSection`: it names the app and the
key whose YAML holds its defaults, and its fields have no defaults of their own. So Python
and the command line cannot build different things:

* ``BiNVSConfig.defaults(crop_size=48)`` is what ``nsd-train model.crop_size=48`` builds;
* ``BiNVSConfig.from_config(cfg.model)`` builds from a composed config (every key given);
* :func:`compose_app` is the whole config of an app as its command line composes it.

A key the YAML lacks, or a key the dataclass does not know, is a :class:`ConfigError`
naming it.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Mapping, Sequence
from importlib.resources import files
from typing import Any, ClassVar, Self

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from nsd.core.errors import ConfigError

__all__ = ["ConfigSection", "compose_app"]



def compose_app(app: str, overrides: Sequence[str] = ()) -> DictConfig:
    """The config of ``app`` (``conf/<app>.yaml``) with command-line style ``overrides``.

    Works inside a running Hydra app too (then its config search path is used).
    """
    if not (files("nsd.conf") / f"{app}.yaml").is_file():
        raise ConfigError(f"no app config {app!r} (conf/{app}.yaml)")
    if GlobalHydra.instance().is_initialized():
        return compose(app, overrides=list(overrides))
    with initialize_config_module("nsd.conf", version_base="1.3"):
        return compose(app, overrides=list(overrides))


@functools.cache
def _default_node(app: str, key: str) -> dict[str, Any]:
    node = OmegaConf.select(compose_app(app), key)
    if node is None:
        raise ConfigError(f"conf/{app}.yaml has no section {key!r}")
    return OmegaConf.to_container(node, resolve=True)


class ConfigSection:
    """Mixin of a settings dataclass whose defaults are one section of a shipped YAML config.

    Subclasses set ``APP`` (the config file, ``conf/<APP>.yaml``), ``KEY`` (the dotted
    section, e.g. ``model``) and, where the section also holds keys read by other
    objects, ``SIBLINGS`` (ignored here). ``validate()``, if the subclass has one, runs
    after construction.
    """

    APP: ClassVar[str]
    KEY: ClassVar[str]
    SIBLINGS: ClassVar[frozenset[str]] = frozenset()

    @classmethod
    def default_mapping(cls) -> dict[str, Any]:
        """The section's values as the shipped YAML gives them (a fresh copy)."""
        return copy.deepcopy(_default_node(cls.APP, cls.KEY))

    @classmethod
    def from_config(cls, node: Mapping[str, Any]) -> Self:
        """Built from a complete section (a composed config's ``KEY``).

        Raises:
            ConfigError: a key is unknown or missing (the message names it).
        """
        return cls._build(node)

    @classmethod
    def _build(cls, node: Mapping[str, Any]) -> Self:
        names = {f.name for f in dataclasses.fields(cls)}
        given = set(node) - cls.SIBLINGS
        unknown, missing = sorted(given - names), sorted(names - given)
        if unknown:
            raise ConfigError(f"{cls.KEY}: unknown keys {unknown}; known {sorted(names)}")
        if missing:
            raise ConfigError(
                f"{cls.KEY}: missing keys {missing} (defaults: conf/{cls.APP}.yaml, {cls.KEY})"
            )
        obj = cls(**{k: node[k] for k in names})
        if hasattr(obj, "validate"):
            obj.validate()
        return obj

    @classmethod
    def defaults(cls, **overrides: Any) -> Self:
        """The shipped defaults with ``overrides`` (keyword per field)."""
        node = cls.default_mapping()
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ConfigError(f"{cls.KEY}: unknown keys {unknown}; known {sorted(names)}")
        node.update(overrides)
        return cls._build({k: node[k] for k in names})
