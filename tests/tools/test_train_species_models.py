"""tools/train_species_models.py: the built-in models are reproduced bit for bit from the seed."""

from __future__ import annotations

import json

import pytest
import torch

import tools.train_species_models as tsm
from netepu.geometry.model import load_geometry_model
from netepu.texture.model import load_texture_model
from nsd.core.atomic import atomic_save_torch
from nsd.export.manifest import sha256_file
from tests.netepu.texture.test_texture import TINY_GEOMETRY_DATA, TINY_TEXTURE_SIZES
from tests.netepu_world import TINY_MODEL
from tools.train_species_models import train_species


def _flat(prefix: str, tree: dict) -> list[str]:
    out = []
    for k, v in tree.items():
        if isinstance(v, dict):
            out += _flat(f"{prefix}.{k}", v)
        else:
            out.append(f"{prefix}.{k}={v}".replace(" ", ""))
    return out


def _tiny(cache) -> list[str]:
    """A tiny world and tiny models for both stages (the recipe's overrides come first)."""
    data = {k: v for k, v in TINY_GEOMETRY_DATA.items() if k not in ("species", "margin", "rig",
                                                                     "heldout_rig")}
    return [
        *_flat("netepu.model", TINY_MODEL), *_flat("netepu.data", data),
        "netepu.data.eval_poses=2", "netepu.data.eval_views_per_pose=2",
        "netepu.data.pool_near=100", "netepu.data.pool_far=100", "netepu.data.pool_foreground=50",
        "+netepu.data.rig.rings=[{count:3,radius:5.0,height:1.5}]", "netepu.data.rig.kind=ring",
        f"netepu.data.cache_dir={cache}", "netepu.optim.batch_size=2", "netepu.eval.eval_views=2",
        *_flat("netepu.texture.model", TINY_TEXTURE_SIZES),
        "netepu.texture.data.textures=[0,2]", "netepu.texture.data.train_poses=2",
        "netepu.texture.data.textures_per_view=2", "netepu.texture.data.eval_poses=2",
        "netepu.texture.data.psnr_cameras=1", "netepu.texture.data.pool=100",
        f"netepu.texture.data.cache_dir={cache}", "netepu.texture.optim.batch_size=2",
        "netepu.texture.optim.points=20", "netepu.texture.optim.reid_whitening_samples=16",
        "netepu.texture.optim.eval_views=1",
    ]


def test_species_model_is_reproduced_bit_for_bit(tmp_path):
    digests = []
    for run in ("a", "b"):
        model, made = train_species("biped", tmp_path / run, threads=1, scale=0.002,
                                    extra=_tiny(tmp_path / "cache"))
        atomic_save_torch(model, tmp_path / f"{run}.pt")
        digests.append(sha256_file(tmp_path / f"{run}.pt"))
    assert made["steps"] == {"geometry": 12, "texture": 4}  # 6,000 and 2,083 steps x 0.002
    assert digests[0] == digests[1]
    # the one file serves both stages, as a geometry and as a texture checkpoint
    geo, _ = load_geometry_model(tmp_path / "a.pt")
    _, geo2, config = load_texture_model(tmp_path / "a.pt")
    assert config["netepu"]["data"]["species"] == "biped"
    assert str(tmp_path / "a") not in str(config)  # not the work folder of the run that made it
    for k, v in geo.state_dict().items():
        assert torch.equal(v, geo2.state_dict()[k])
    assert set(model) == {"format", "config", "modules", "step"}  # no optimiser, no RNG state
    # the texture stage on run a's geometry run: the same file, the run's hash recorded
    model_c, made_c = train_species("biped", tmp_path / "c", threads=1, scale=0.002,
                                    extra=_tiny(tmp_path / "cache"),
                                    geometry_from=tmp_path / "a" / "geometry")
    atomic_save_torch(model_c, tmp_path / "c.pt")
    assert sha256_file(tmp_path / "c.pt") == digests[0]
    assert not (tmp_path / "c" / "geometry").exists()
    # the geometry's figures read back from its metrics.csv (json: NaN, the tiny world's depth
    # error, equals itself)
    assert json.dumps(made_c["figures"], sort_keys=True) == json.dumps(made["figures"],
                                                                       sort_keys=True)
    assert made_c["geometry_from_sha256"] == sha256_file(tmp_path / "a" / "geometry" /
                                                         "checkpoint.pt")
    # a geometry run of another step count or config is refused, naming what differs
    with pytest.raises(SystemExit, match=r"step 12 \(recipe 18\)"):
        train_species("biped", tmp_path / "d", threads=1, scale=0.003,
                      extra=_tiny(tmp_path / "cache"), geometry_from=tmp_path / "a" / "geometry")
    with pytest.raises(SystemExit, match=r"netepu\.optim\.batch_size 2 \(recipe 3\)"):
        train_species("biped", tmp_path / "d", threads=1, scale=0.002,
                      extra=[*_tiny(tmp_path / "cache"), "netepu.optim.batch_size=3"],
                      geometry_from=tmp_path / "a" / "geometry")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    (tmp_path / "junk" / "metrics.csv").write_text("step\n")
    with pytest.raises(SystemExit, match=r"--geometry-from .*junk: checkpoint "):
        train_species("biped", tmp_path / "d", threads=1, scale=0.002,
                      extra=_tiny(tmp_path / "cache"), geometry_from=tmp_path / "junk")
    with pytest.raises(SystemExit, match=r"no checkpoint\.pt"):
        train_species("biped", tmp_path / "d", threads=1, scale=0.002,
                      extra=_tiny(tmp_path / "cache"), geometry_from=tmp_path / "a")


def test_pose_stage_alone_refits_the_recorded_file_and_refuses_another(tmp_path, monkeypatch):
    model, made = train_species("biped", tmp_path / "run", threads=1, scale=0.002,
                                extra=_tiny(tmp_path / "cache"))
    source = tmp_path / "biped.pt"
    atomic_save_torch(model, source)
    manifest = tmp_path / "models.json"
    manifest.write_text(json.dumps({"models": {"biped": {
        "file": "biped.pt", "sha256": sha256_file(source), **made}}}))
    monkeypatch.setitem(tsm.RECIPES, "biped", {**tsm.RECIPES["biped"], "pose_steps": 3})
    refit, made2 = tsm._pose_only("biped", source, manifest, threads=1)
    assert made2["steps"] == {**made["steps"], "pose": 3}
    assert made2["pose_from_sha256"] == sha256_file(source)
    assert made2["figures"]["texture"] == made["figures"]["texture"]  # carried over
    assert {"round_trip_own_after_mm", "feature_change"} <= set(made2["figures"]["pose_code"])
    before, after = model["modules"]["geometry"], refit["modules"]["geometry"]
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith(("encoder.", "decoder.mlp_pos.")) for k in changed)
    assert refit["modules"]["texture"] is not None
    # a file that is not the one models.json records: refused, naming it
    other = tmp_path / "other.pt"
    atomic_save_torch(refit, other)
    with pytest.raises(SystemExit, match=r"other\.pt"):
        tsm._pose_only("biped", other, manifest, threads=1)
    with pytest.raises(SystemExit, match="no such file"):
        tsm._pose_only("biped", tmp_path / "missing.pt", manifest, threads=1)
    # the refitted file, once recorded, is not refitted a second time
    manifest.write_text(json.dumps({"models": {"biped": {
        "file": "other.pt", "sha256": sha256_file(other), **made2}}}))
    with pytest.raises(SystemExit, match="refitted already"):
        tsm._pose_only("biped", other, manifest, threads=1)


def test_check_says_what_differs():
    """The same checkpoint: nothing; a changed tensor names its module, name and largest
    difference; a key added to the config names the key (the text --check prints)."""
    def model():
        return {"modules": {"texture": {"w": torch.ones(3), "b": torch.zeros(2)}},
                "config": {"netepu": {"texture": {"k": 20}}}, "step": 5}

    a, b = model(), model()
    assert tsm.model_differences(a, b) == []
    a["modules"]["texture"]["w"][1] += 0.25
    a["config"]["netepu"]["texture"]["new_key"] = False
    assert tsm.model_differences(a, b) == [
        "texture.w: largest difference 0.25 (largest entry 1)",
        "config netepu.texture.new_key: only in the retrained (False)",
    ]
