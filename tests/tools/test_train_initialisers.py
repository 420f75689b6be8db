"""tools/train_initialisers.py: an initialiser is reproduced bit for bit from its recipe."""

from __future__ import annotations

import json
import shutil

import torch

from netepu.geometry.initialiser import load_initialiser
from netepu.pipeline.species_models import MODELS
from nsd.export.manifest import sha256_file
from tools import train_initialisers


def test_a_tiny_recipe_twice_gives_the_same_file(tmp_path, monkeypatch):
    """Trained into a models folder, the file and its manifest entry are written; --check
    retrains and finds the same SHA-256; a changed seed does not. Two trainings in one process
    take different times: the file records none (it once recorded its minutes, and a rerun
    that took 0.01 minutes longer gave other bytes)."""
    shutil.copy(MODELS / "models.json", tmp_path / "models.json")
    tiny = {"poses": 4, "cameras": 4, "steps": 3, "batch": 2, "heldout": 1, "seed": 0,
            "threads": 1}
    monkeypatch.setattr(train_initialisers, "RECIPE", tiny)
    assert train_initialisers.main(["biped", "--out", str(tmp_path)]) == 0
    entry = json.loads((tmp_path / "models.json").read_text())["initialisers"]["biped"]
    assert entry["steps"] == 3 and (tmp_path / entry["file"]).is_file()
    assert load_initialiser(tmp_path / entry["file"]).cfg.n_keypoints == 17
    assert train_initialisers.main(["biped", "--out", str(tmp_path), "--check"]) == 0
    monkeypatch.setattr(train_initialisers, "RECIPE", {**tiny, "seed": 1})
    assert train_initialisers.main(["biped", "--out", str(tmp_path), "--check"]) == 1


def test_a_shipped_file_that_records_its_minutes_passes_the_check_by_its_weights(
        tmp_path, monkeypatch, capsys):
    """Files shipped before the fix hold their training's minutes: --check then compares
    config and weights bit for bit, and still finds a changed seed."""
    shutil.copy(MODELS / "models.json", tmp_path / "models.json")
    tiny = {"poses": 4, "cameras": 4, "steps": 2, "batch": 2, "heldout": 1, "seed": 0,
            "threads": 1}
    monkeypatch.setattr(train_initialisers, "RECIPE", tiny)
    assert train_initialisers.main(["biped", "--out", str(tmp_path)]) == 0
    shipped = tmp_path / "biped_initialiser.pt"
    old = torch.load(shipped, weights_only=True)
    old["trained"]["minutes"] = 12.34  # as the files made before 2026-12-01
    torch.save(old, shipped)
    manifest = json.loads((tmp_path / "models.json").read_text())
    manifest["initialisers"]["biped"]["sha256"] = sha256_file(shipped)  # the manifest's own
    (tmp_path / "models.json").write_text(json.dumps(manifest))
    capsys.readouterr()
    assert train_initialisers.main(["biped", "--out", str(tmp_path), "--check"]) == 0
    assert "the same weights" in capsys.readouterr().out
    monkeypatch.setattr(train_initialisers, "RECIPE", {**tiny, "seed": 1})
    assert train_initialisers.main(["biped", "--out", str(tmp_path), "--check"]) == 1
    assert "DIFFERENT" in capsys.readouterr().out
