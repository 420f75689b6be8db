"""The built-in NeTePu models: which model a run takes, and the shipped files themselves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from netepu.geometry.model import load_geometry_model
from netepu.pipeline.species_models import (
    BUILTIN,
    MODELS,
    builtin_initialisers,
    builtin_models,
    resolve_initialiser,
    resolve_scene_models,
    resolve_species_models,
    scene_species,
)
from netepu.texture.model import load_texture_model
from nsd.core.errors import ConfigError
from nsd.export.manifest import sha256_file
from nsd.synth import tiny_config, write_scene


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    return write_scene(tiny_config(), tmp_path_factory.mktemp("species") / "scene")


def _folder(tmp_path, species=("biped",)):
    entries = {s: {"file": f"{s}.pt", "sha256": f"{s}-hash"} for s in species}
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "models.json").write_text(json.dumps({"models": entries}))
    return tmp_path


def test_scene_species_reads_what_the_scene_declares(synth_scene, tiny_scene, tmp_path):
    assert scene_species(synth_scene) == ["biped"]
    assert scene_species(tiny_scene) == []  # footage without gt/scene.json
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "scene.json").write_text("{not json")
    assert scene_species(tmp_path) == []


def test_builtin_takes_the_model_of_the_scenes_species(synth_scene, tmp_path):
    folder = _folder(tmp_path / "models")
    m = resolve_species_models("auto", BUILTIN, BUILTIN, synth_scene, folder)
    assert m.geometry == m.texture == str(folder / "biped.pt")  # one file serves both
    assert m.key_geometry == m.key_texture == "builtin:biped-hash"  # keyed by content
    assert m.why_geometry == m.why_texture == ""
    own = resolve_species_models("auto", "my/geo.pt", None, synth_scene, folder)
    assert (own.geometry, own.key_geometry, own.texture) == ("my/geo.pt", "my/geo.pt", None)
    assert own.why_texture == "netepu.texture=null"


def test_the_initialiser_of_the_scenes_species(synth_scene, tiny_scene, tmp_path):
    """builtin: the shipped initialiser of the scene's species, keyed by its hash; a path as
    given; null, footage without a species, or a species without one shipped: none, and why."""
    folder = _folder(tmp_path / "models", ("biped", "quadruped"))
    manifest = json.loads((folder / "models.json").read_text())
    manifest["initialisers"] = {"biped": {"file": "biped_initialiser.pt", "sha256": "b-init"}}
    (folder / "models.json").write_text(json.dumps(manifest))
    assert resolve_initialiser(BUILTIN, "auto", synth_scene, folder) == (
        str(folder / "biped_initialiser.pt"), "builtin:b-init", "")
    assert resolve_initialiser("my/init.pt", "auto", tiny_scene, folder)[:2] == (
        "my/init.pt", "my/init.pt")
    none, key, why = resolve_initialiser(None, "auto", synth_scene, folder)
    assert none is None and key is None and why == "netepu.keypoints.initialiser=null"
    assert "does not declare its species" in resolve_initialiser(
        BUILTIN, "auto", tiny_scene, folder)[2]
    path, _, why = resolve_initialiser(BUILTIN, "quadruped", synth_scene, folder)
    assert path is None and why == "no built-in quadruped initialiser is shipped"
    m = resolve_species_models("auto", BUILTIN, BUILTIN, synth_scene, folder, initialiser=BUILTIN)
    assert (m.initialiser, m.key_initialiser) == (str(folder / "biped_initialiser.pt"),
                                                  "builtin:b-init")
    own = resolve_species_models("auto", "my/geo.pt", BUILTIN, synth_scene, folder,
                                 initialiser=BUILTIN)  # another body: no shipped initialiser
    assert own.initialiser is None and "your own netepu.geometry" in own.why_initialiser


def test_shipped_initialisers_fit_their_species_models():
    """Every shipped initialiser loads with weights_only, matches its manifest hash, and was
    made for its species model's keypoints and body radius."""
    from netepu.geometry.initialiser import load_initialiser

    inits = builtin_initialisers()
    assert set(inits) <= set(builtin_models())
    for species, entry in inits.items():
        path = MODELS / entry["file"]
        assert sha256_file(path) == entry["sha256"]
        net = load_initialiser(path)
        model, config = load_geometry_model(MODELS / builtin_models()[species]["file"])
        assert net.cfg.n_keypoints == model.n_keypoints
        assert net.cfg.radius == pytest.approx(float(config["netepu"]["data"]["radius"]))


def test_builtin_says_why_when_no_model_fits(synth_scene, tiny_scene, tmp_path):
    folder = _folder(tmp_path / "models")
    m = resolve_species_models("auto", BUILTIN, BUILTIN, tiny_scene, folder)
    assert m.geometry is None and m.texture is None
    assert "does not declare its species" in m.why_geometry and "netepu.species" in m.why_texture
    m = resolve_species_models("quadruped", BUILTIN, BUILTIN, synth_scene, folder)
    assert m.geometry is None and "no built-in quadruped model" in m.why_geometry
    m = resolve_species_models("biped", BUILTIN, BUILTIN, tiny_scene, folder)  # the user says
    assert m.geometry == str(folder / "biped.pt")
    with pytest.raises(ConfigError, match=r"netepu\.species"):
        resolve_species_models("cow", BUILTIN, BUILTIN, tiny_scene, folder)


def test_a_scene_of_two_species_takes_the_models_of_both(tmp_path, synth_scene):
    """auto on a scene that declares two species, or mixed: one model set per species, each
    with its initialiser; one species per scene, or checkpoints of the user's own: one set."""
    scene = write_scene(tiny_config(species=["biped", "quadruped"]), tmp_path / "scene")
    folder = _folder(tmp_path / "m", ("biped", "quadruped"))
    m = resolve_species_models("auto", BUILTIN, BUILTIN, scene, folder)  # one set cannot
    assert m.geometry is None and "biped and quadruped" in m.why_geometry
    for species in ("auto", "mixed"):
        sets = resolve_scene_models(species, BUILTIN, BUILTIN, scene, folder, BUILTIN)
        assert [s.species for s in sets] == ["biped", "quadruped"]
        assert [s.geometry for s in sets] == [str(folder / f"{x}.pt") for x in ("biped",
                                                                              "quadruped")]
        assert [s.key_texture for s in sets] == ["builtin:biped-hash", "builtin:quadruped-hash"]
    no_texture = resolve_scene_models("auto", BUILTIN, None, scene, folder)
    assert [s.texture for s in no_texture] == [None, None] and len(no_texture) == 2
    one = resolve_scene_models("auto", BUILTIN, BUILTIN, synth_scene, folder)
    assert [s.species for s in one] == ["biped"]
    own = resolve_scene_models("auto", "my/geo.pt", BUILTIN, scene, folder)
    assert len(own) == 1 and own[0].geometry == "my/geo.pt" and own[0].texture is None
    mixed_on_biped_scene = resolve_scene_models("mixed", BUILTIN, BUILTIN, synth_scene, folder)
    assert len(mixed_on_biped_scene) == 2  # mixed: every shipped species, whatever is declared
    for geometry, texture in (("my/geo.pt", BUILTIN), (BUILTIN, "my/tex.pt"), (None, BUILTIN)):
        with pytest.raises(ConfigError, match=r"netepu\.species=mixed"):
            resolve_scene_models("mixed", geometry, texture, scene, folder)
    only = resolve_scene_models("mixed", BUILTIN, BUILTIN, scene, _folder(tmp_path / "o"))
    assert [s.species for s in only] == ["biped"]  # one species shipped: that one


def test_the_shipped_models_are_what_the_manifest_says():
    shipped = builtin_models()
    assert "biped" in shipped  # the default scene's species
    for species, entry in shipped.items():
        path = MODELS / entry["file"]
        assert sha256_file(path) == entry["sha256"], path
        _, geo, config = load_texture_model(path)  # weights_only=True
        geo2, _ = load_geometry_model(path)
        assert config["netepu"]["data"]["species"] == species
        for k, v in geo.state_dict().items():
            assert np.array_equal(v.numpy(), geo2.state_dict()[k].numpy())


def test_explicit_checkpoints_need_no_species(tmp_path, monkeypatch):
    """Paths (or null) for both models: the scene's species is never read, so a scene of two
    species (or none) runs with the user's own checkpoints."""
    import netepu.pipeline.species_models as sm

    scene = write_scene(tiny_config(species=["biped", "quadruped"]), tmp_path / "scene")
    monkeypatch.setattr(sm, "scene_species", lambda s: pytest.fail("the species was read"))
    m = resolve_species_models("auto", "my/geometry.pt", None, scene, _folder(tmp_path / "m"))
    assert m.geometry == "my/geometry.pt" and m.texture is None and m.why_geometry == ""
    assert m.key_geometry == "my/geometry.pt"
