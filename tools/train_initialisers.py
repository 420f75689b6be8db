"""Make the built-in learned initialisers of inverse rendering (netepu/geometry/initialiser.py).

    .venv/bin/python tools/train_initialisers.py biped            # ~30 min on one core
    .venv/bin/python tools/train_initialisers.py biped --check    # retrain, compare SHA-256

For a species: render the training poses (``RECIPE``: poses, cameras per pose, seed), then
train the initialiser for a step budget (never minutes, which depend on the machine) on one
CPU thread (:mod:`netepu.geometry.initialiser_training`). The body radius and the keypoints
come from the shipped geometry model of the species, so the two always agree. The file goes
to ``netepu/pipeline/models/<species>_initialiser.pt``; ``models.json`` records under
``initialisers`` how it was made, its SHA-256 and its held-out error.

The same torch build, CPU kind and thread count reproduce the file bit for bit (``--check``;
the wall time goes to ``models.json`` only, and a file shipped before 2026-12-01, which also
recorded it, passes when its config and weights are the same bit for bit).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netepu.geometry.initialiser import InitialiserConfig  # noqa: E402
from netepu.geometry.initialiser_training import render_bank, train_initialiser  # noqa: E402
from netepu.geometry.model import load_geometry_model  # noqa: E402
from netepu.pipeline.species_models import MODELS, builtin_models  # noqa: E402
from nsd.export.manifest import sha256_file  # noqa: E402
from tools.benchlib import ship_file  # noqa: E402

# the same for both species: 3,000 rendered poses x 12 cameras, 3,000 steps of 32 samples
# (about 30 minutes on one core here; docs/netepu.md "A learned initialiser")
RECIPE = {"poses": 3000, "cameras": 12, "steps": 3000, "batch": 32, "heldout": 256, "seed": 0,
          "threads": 1}


def _same_weights(made: Path, shipped: Path) -> bool:
    """Whether two initialiser files hold the same config and weights, bit for bit (files
    made before 2026-12-01 also recorded their training's minutes, so their bytes differ)."""
    if not shipped.is_file():
        return False
    a, b = (torch.load(p, map_location="cpu", weights_only=True) for p in (made, shipped))
    return (a["config"] == b["config"] and a["state"].keys() == b["state"].keys()
            and all(torch.equal(a["state"][k], b["state"][k]) for k in a["state"]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("species", choices=sorted(builtin_models()))
    ap.add_argument("--check", action="store_true",
                    help="train again and compare the SHA-256 with the shipped file's")
    ap.add_argument("--out", type=Path, default=MODELS, help="the models folder")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(RECIPE["threads"])
    geometry, config = load_geometry_model(MODELS / builtin_models()[args.species]["file"])
    cfg = InitialiserConfig(geometry.n_keypoints, float(config["netepu"]["data"]["radius"]))
    start = time.perf_counter()
    bank = render_bank(args.species, cfg.radius, RECIPE["poses"], RECIPE["cameras"],
                       RECIPE["seed"])
    with tempfile.TemporaryDirectory(prefix="initialiser-") as tmp:
        name = f"{args.species}_initialiser.pt"
        target = Path(tmp) / name if args.check else args.out / name
        res = train_initialiser(bank, cfg, 0.0, str(target), seed=RECIPE["seed"],
                                batch=RECIPE["batch"], heldout=RECIPE["heldout"],
                                max_steps=RECIPE["steps"])
        digest = sha256_file(target)
        manifest_path = args.out / "models.json"
        manifest = json.loads(manifest_path.read_text())  # read now: the other species may
        if args.check:                                     # have been written meanwhile
            shipped = manifest.get("initialisers", {}).get(args.species, {}).get("sha256")
            same = digest == shipped or _same_weights(target, args.out / name)
            print(f"{args.species}: retrained {digest}\n  shipped {shipped}\n" + (
                "bit for bit the same" if digest == shipped else
                "the same weights (the shipped file also records its training time)" if same
                else "DIFFERENT"))
            return 0 if same else 1
    ship_file(manifest_path, manifest, "initialisers", args.species, target, digest, {
        **RECIPE, "config": cfg.to_dict(),
        "minutes": round((time.perf_counter() - start) / 60, 1),
        "heldout_mpjpe_mm": {"mean": round(res.heldout_mean, 1),
                             "median": round(res.heldout_median, 1)}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
