"""tools/train_initialisers.py: an initialiser is reproduced bit for bit from its recipe."""

from __future__ import annotations

import json
import shutil

from netepu.geometry.initialiser import load_initialiser
from netepu.pipeline.species_models import MODELS
from tools import train_initialisers


def test_a_tiny_recipe_twice_gives_the_same_file(tmp_path, monkeypatch):
    """Trained into a models folder, the file and its manifest entry are written; --check
    retrains and finds the same SHA-256; a changed seed does not."""
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
