"""The built-in NeTePu models: one per species, trained on the synthetic world, shipped as
package data so that ``nsd-run`` renders, encodes and re-identifies without a model of
the user's own.

A species model is one ``netepu-train stage=texture`` checkpoint stripped to its weights
and config (no optimiser or random state): it holds the geometry model the texture model
was trained on, so it serves as the geometry model of the keypoints stage and the texture
model of the texture stage. ``models/models.json`` says how each file was made (the
``netepu-train`` overrides, seed, steps, threads, torch), its SHA-256 and its held-out
figures; ``tools/train_species_models.py`` makes them (docs/netepu.md, "Built-in models").

``nsd-run``'s ``netepu.geometry`` / ``netepu.texture`` take ``builtin`` (the default: the
model of ``netepu.species``), a checkpoint path, or null (stage off). ``netepu.species:
auto`` reads the species the scene declares (``gt/scene.json`` of an ``nsd-synth`` scene);
footage that does not declare one needs ``netepu.species=biped`` or ``quadruped``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from nsd.core.errors import ConfigError

__all__ = [
    "BUILTIN",
    "MODELS",
    "SPECIES",
    "SpeciesModels",
    "builtin_initialisers",
    "builtin_models",
    "resolve_initialiser",
    "resolve_scene_models",
    "resolve_species_models",
    "scene_species",
]

BUILTIN = "builtin"  # the value of netepu.geometry / netepu.texture that picks the shipped model
SPECIES = ("auto", "biped", "quadruped", "mixed")  # netepu.species (auto: the scene's own;
# mixed: every shipped species, each subject taking the one that fits it)
MODELS = Path(__file__).with_name("models")  # package data: <species>.pt and models.json


def builtin_models(folder: Path = MODELS) -> dict[str, dict]:
    """The manifest of the shipped models, ``{species: {"file", "sha256", ...}}`` ({} if none)."""
    path = folder / "models.json"
    if not path.is_file():
        return {}
    return json.loads(path.read_text())["models"]


def builtin_initialisers(folder: Path = MODELS) -> dict[str, dict]:
    """The shipped learned initialisers of inverse rendering, ``{species: {"file", "sha256",
    ...}}`` (``initialisers`` in ``models.json``, made by ``tools/train_initialisers.py``)."""
    path = folder / "models.json"
    if not path.is_file():
        return {}
    return json.loads(path.read_text()).get("initialisers", {})


def scene_species(scene: str | Path) -> list[str]:
    """The species a scene declares (sorted, distinct): those of the individuals in
    ``gt/scene.json`` of an ``nsd-synth`` scene; [] for footage that declares none."""
    path = Path(scene) / "gt" / "scene.json"
    if not path.is_file():
        return []
    try:
        individuals = json.loads(path.read_text()).get("individuals", [])
        return sorted({str(i["species"]) for i in individuals})
    except (ValueError, TypeError, KeyError, AttributeError):  # not an nsd-synth scene file
        return []


@dataclass(frozen=True)
class SpeciesModels:
    """The checkpoints the keypoints and texture stages use (None: that stage is off, and
    ``why`` says why), and the settings that key those stages (a shipped file by its hash);
    the keypoints stage's learned initialiser (None: cold starts screen the templates)."""

    geometry: str | None
    texture: str | None
    why_geometry: str
    why_texture: str
    key_geometry: str | None
    key_texture: str | None
    initialiser: str | None = None
    key_initialiser: str | None = None
    why_initialiser: str = "netepu.keypoints.initialiser=null"
    species: str = ""  # the built-in models' species ("" for checkpoints of the user's own)


def _builtin(species: str, scene: str | Path, folder: Path) -> tuple[dict | None, str]:
    """(manifest entry, "") of the shipped model to use, or (None, why not)."""
    if species == "auto":
        found = scene_species(scene)
        if not found:
            return None, ("the scene does not declare its species; set netepu.species=biped or "
                          "quadruped for the built-in models, or give your own checkpoints")
        if len(found) > 1:
            return None, (f"the scene holds {' and '.join(found)}; the built-in models are one "
                          "per species: set netepu.species")
        species = found[0]
    entry = builtin_models(folder).get(species)
    if entry is None:
        return None, f"no built-in {species} model is shipped (give netepu.geometry / texture)"
    return {**entry, "species": species, "path": str(folder / entry["file"])}, ""


def resolve_species_models(
    species: str, geometry: str | None, texture: str | None, scene: str | Path,
    folder: Path = MODELS, initialiser: str | None = None,
) -> SpeciesModels:
    """The NeTePu checkpoints of a run from ``netepu.species``, ``netepu.geometry``,
    ``netepu.texture`` and ``netepu.keypoints.initialiser`` (each ``builtin``, a path or
    None).

    Raises:
        ConfigError: an unknown species.
    """
    if species not in SPECIES:
        raise ConfigError(f"netepu.species must be one of {SPECIES}, got {species!r}")
    if species == "mixed":
        return SpeciesModels(None, None, *["netepu.species=mixed takes one model per species "
                                           "(resolve_scene_models)"] * 2, None, None)
    # the scene's species is read only when a built-in model is asked for
    entry, why = _builtin(species, scene, folder) if BUILTIN in (
        str(geometry), str(texture)) else (None, "")
    paths, whys, keys = [], [], []
    for key, value in (("geometry", geometry), ("texture", texture)):
        if value is None:
            paths.append(None)
            whys.append(f"netepu.{key}=null")
            keys.append(None)
        elif str(value) == BUILTIN:
            paths.append(entry["path"] if entry else None)
            whys.append(f"built-in model: {why}" if not entry else "")
            keys.append(f"builtin:{entry['sha256']}" if entry else None)
        else:
            paths.append(str(value))
            whys.append("")
            keys.append(str(value))
    if str(initialiser) == BUILTIN and str(geometry) != BUILTIN:  # made for another body
        init, init_key, init_why = None, None, (
            "the built-in initialiser goes with the built-in geometry model; with your own "
            "netepu.geometry give netepu.keypoints.initialiser a checkpoint of your own")
    else:
        init, init_key, init_why = resolve_initialiser(initialiser, species, scene, folder)
    return SpeciesModels(paths[0], paths[1], whys[0], whys[1], keys[0], keys[1], init, init_key,
                         init_why, entry["species"] if entry else "")


def resolve_scene_models(
    species: str, geometry: str | None, texture: str | None, scene: str | Path,
    folder: Path = MODELS, initialiser: str | None = None,
) -> list[SpeciesModels]:
    """The NeTePu models of a run: one :class:`SpeciesModels`, or one per species where the
    run holds several (``netepu.species=mixed``: every shipped species; ``auto`` on a scene
    that declares several), each with the built-in models of its species.

    Raises:
        ConfigError: an unknown species, or ``mixed`` with checkpoints of the user's own (a
            model of another body cannot tell which species a subject is).
    """
    own = [v for v in (geometry, texture) if v is not None and str(v) != BUILTIN]
    if species == "mixed" and (own or geometry is None):
        raise ConfigError("netepu.species=mixed takes the built-in models of every species (their "
                          "geometry models tell which species a subject is): set "
                          "netepu.geometry=builtin and netepu.texture to builtin or null, or "
                          "netepu.species=auto with checkpoints of your own")
    several = sorted(builtin_models(folder)) if species == "mixed" else (
        scene_species(scene) if species == "auto" and not own and str(geometry) == BUILTIN
        else [])
    if len(several) < 2:
        if species == "mixed":  # fewer than two species shipped: the one there is
            species = several[0] if several else "biped"
        return [resolve_species_models(species, geometry, texture, scene, folder, initialiser)]
    return [resolve_species_models(s, geometry, texture, scene, folder, initialiser)
            for s in several]


def resolve_initialiser(value: str | None, species: str, scene: str | Path,
                        folder: Path = MODELS) -> tuple[str | None, str | None, str]:
    """The learned initialiser of the keypoints stage from ``netepu.keypoints.initialiser``
    (``builtin``, a checkpoint path, or None): (path, the stage's key, why there is none).

    Without one, cold starts screen the template poses (:mod:`netepu.geometry.inverse`).
    """
    if value is None:
        return None, None, "netepu.keypoints.initialiser=null"
    if str(value) != BUILTIN:
        return str(value), str(value), ""
    entry, why = _builtin(species, scene, folder)
    if entry is None:
        return None, None, why
    init = builtin_initialisers(folder).get(entry["species"])
    if init is None:
        return None, None, f"no built-in {entry['species']} initialiser is shipped"
    return str(folder / init["file"]), f"builtin:{init['sha256']}", ""
