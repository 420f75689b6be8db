"""Make the built-in NeTePu models that ``nsd-run`` uses (netepu/pipeline/species_models.py).

    .venv/bin/python tools/train_species_models.py biped            # ~40 min on two cores
    .venv/bin/python tools/train_species_models.py biped --check    # retrain, compare SHA-256
    .venv/bin/python tools/train_species_models.py quadruped --pose-from OLD.pt  # last stage only
    .venv/bin/python tools/train_species_models.py quadruped --geometry-from RUN  # skip stage 1

For a species: ``netepu-train`` geometry on the synthetic world (``RECIPES``: overrides and
steps), then the texture stage from that geometry, both with the trainer's fixed seed,
on the recipe's CPU threads and with step budgets (never minutes, which depend on the
machine); then, where the recipe has ``pose_steps``, the pose code refitted on fresh poses
(:mod:`netepu.geometry.pose_code`, seeded). ``--pose-from`` runs that last stage alone on a
file the first two made (its SHA-256 is recorded as ``pose_from_sha256``); ``--geometry-from``
starts at the texture stage from a geometry run of the recipe made earlier (an earlier
``--work`` folder's ``geometry/``: its config and step count are checked against the recipe,
its checkpoint's SHA-256 is recorded as ``geometry_from_sha256``; the same run gives the
same file as training all stages). The texture
checkpoint (which holds its geometry model) is stripped to its config and weights and
written to ``netepu/pipeline/models/<species>.pt``; ``models.json`` records how it was made,
its SHA-256 and the final held-out figures of the stages.

The same torch build, CPU kind and thread count reproduce the file bit for bit: ``--check``
trains again into a temporary folder and compares the hash with the manifest's (other CPUs
may round matrix products differently and give a different, equally good file).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from omegaconf import OmegaConf  # noqa: E402

from netepu.cli.train import run  # noqa: E402
from netepu.geometry.data import DataConfig  # noqa: E402
from netepu.geometry.model import geometry_model_from_state  # noqa: E402
from netepu.geometry.pose_code import PoseCodeSettings, refit_pose_code  # noqa: E402
from netepu.pipeline.species_models import MODELS  # noqa: E402
from nsd.core.atomic import atomic_save_torch  # noqa: E402
from nsd.core.config import compose_app  # noqa: E402
from nsd.core.errors import CheckpointError  # noqa: E402
from nsd.core.trainer import CHECKPOINT_FORMAT, load_checkpoint  # noqa: E402
from nsd.export.manifest import sha256_file  # noqa: E402
from tools.benchlib import evaluations, ship_file  # noqa: E402

# netepu-train overrides, step budgets and threads per species (docs/netepu.md, "Built-in
# models"; the biped's 6,000 geometry steps on two threads are the 30 minutes of issue 26,
# docs/benchmarks/netepu_geometry_recipe.md)
RECIPES = {
    "biped": {
        "geometry": ["netepu/data=biped", "netepu.model.renderer.k=12",
                     "netepu.optim.lr_decay_every=4000"],
        "geometry_steps": 6000,
        "texture": [],
        "texture_steps": 2083,
        "pose_steps": 0,
        "threads": 2,
    },
    "quadruped": {
        "geometry": ["netepu/data=quadruped", "netepu.optim.lr_decay_every=3500"],
        "geometry_steps": 5000,
        "texture": ["netepu.texture.model.renderer.k=20"],
        "texture_steps": 2083,
        # docs/netepu.md "The pose code": its decoder's floor on fresh poses 60 -> 27 mm
        "pose_steps": 2400,
        "threads": 2,
    },
}
FIGURES = ("heldout_poses", "heldout_cameras", "reid")  # final evaluations kept in the manifest


def _config(overrides: list[str], steps: int, threads: int):
    return compose_app("netepu_train", [
        *overrides, f"trainer.max_steps={steps}", "trainer.max_minutes=0",
        "trainer.progress=false", f"threads={threads}", "device=cpu",
    ])


def _train(overrides: list[str], steps: int, threads: int, out: Path) -> dict[str, float]:
    return run(_config(overrides, steps, threads), out)


def _flat(tree: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in tree.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _earlier_geometry(folder: Path, overrides: list[str], steps: int,
                      threads: int) -> tuple[dict[str, float], float]:
    """The final held-out figures and minutes of the geometry run in ``folder``, after checking
    that it is this recipe's: its step count and every config value the recipe sets (values
    left ``null`` to be filled in from the species excepted).

    Raises:
        SystemExit: naming the folder and what differs.
    """
    if not (folder / "checkpoint.pt").is_file() or not (folder / "metrics.csv").is_file():
        raise SystemExit(f"--geometry-from {folder}: no checkpoint.pt and metrics.csv there "
                         f"(give the geometry/ folder of an earlier --work)")
    try:
        state = load_checkpoint(folder)
    except CheckpointError as e:
        raise SystemExit(f"--geometry-from {folder}: {e}") from None
    wanted = _flat(OmegaConf.to_container(_config(overrides, steps, threads), resolve=True))
    have = _flat(state["config"])
    differ = [f"{k} {have.get(k, 'missing')!r} (recipe {v!r})" for k, v in wanted.items()
              if v is not None and have.get(k, "missing") != v]
    if int(state["step"]) != steps:
        differ.insert(0, f"step {state['step']} (recipe {steps})")
    if differ:
        raise SystemExit(f"--geometry-from {folder}: not this recipe's geometry run: "
                         + "; ".join(differ[:5]) + ("; ..." if len(differ) > 5 else ""))
    rows = evaluations(folder)
    if not rows or int(rows[-1]["step"]) != steps:
        raise SystemExit(f"--geometry-from {folder}: metrics.csv holds no final evaluation")
    final = {k.removeprefix("eval/"): float(v) for k, v in rows[-1].items()
             if k.startswith("eval/") and v}
    return final, float(rows[-1]["minutes"])


def _figures(metrics: dict[str, float]) -> dict[str, float]:
    return {k: round(float(v), 6) for k, v in sorted(metrics.items())
            if k.split("/")[0] in FIGURES}


def refit_pose(model: dict, made: dict, steps: int, threads: int) -> None:
    """Refit the pose code of the stripped checkpoint ``model`` (its geometry weights replaced
    in place) for ``steps`` steps on ``threads`` threads; ``made`` gets the stage's steps,
    minutes and figures."""
    t0 = time.perf_counter()
    torch.set_num_threads(threads)
    geo, config = geometry_model_from_state(model, "the pose stage's input")
    figures = refit_pose_code(geo, DataConfig.from_mapping(config["netepu"]["data"]),
                              PoseCodeSettings(steps=steps),
                              progress=lambda step, loss: print(f"pose code: step {step}, "
                                                                f"loss {loss:.4f}", flush=True))
    model["modules"]["geometry"] = {k: v.detach().clone() for k, v in geo.state_dict().items()}
    made["steps"] = {**made.get("steps", {}), "pose": steps}
    made["minutes"] = {**made.get("minutes", {}),
                       "pose": round((time.perf_counter() - t0) / 60, 1)}
    made["figures"] = {**made.get("figures", {}),
                       "pose_code": {k: round(v, 6) for k, v in figures.items()}}


def train_species(species: str, work: Path, threads: int, scale: float = 1.0,
                  extra: list[str] | None = None,
                  geometry_from: Path | None = None) -> tuple[dict, dict]:
    """Train ``species``'s geometry then texture model in ``work``; returns (stripped
    checkpoint, recipe with the figures). ``scale`` shrinks the step budgets and ``extra``
    adds overrides to both stages (tests: a tiny world). ``geometry_from``: the folder of an
    earlier geometry run of this recipe, used instead of training the geometry again."""
    recipe = RECIPES[species]
    extra = list(extra or [])
    steps = {s: max(1, round(recipe[f"{s}_steps"] * scale)) for s in ("geometry", "texture")}
    geometry_overrides = [*recipe["geometry"], *extra]
    t0 = time.perf_counter()
    if geometry_from is None:
        geometry_from = work / "geometry"
        geo = _train(geometry_overrides, steps["geometry"], threads, geometry_from)
        geo_minutes = (time.perf_counter() - t0) / 60
        earlier = {}
    else:
        geo, geo_minutes = _earlier_geometry(geometry_from, geometry_overrides,
                                             steps["geometry"], threads)
        earlier = {"geometry_from_sha256": sha256_file(geometry_from / "checkpoint.pt")}
    t1 = time.perf_counter()
    tex = _train([*recipe["texture"], *extra, "stage=texture",
                  f"init_from={geometry_from / 'checkpoint.pt'}"],
                 steps["texture"], threads, work / "texture")
    t2 = time.perf_counter()
    state = load_checkpoint(work / "texture")
    config = {**state["config"], "init_from": f"{species} geometry of {Path(__file__).name}"}
    model = {"format": CHECKPOINT_FORMAT, "config": config,  # no path of this machine in it
             "modules": {k: state["modules"][k] for k in ("geometry", "texture")},
             "step": int(state["step"])}
    made = {
        "species": species, "threads": threads, "steps": steps,
        "overrides": {"geometry": geometry_overrides,
                      "texture": [*recipe["texture"], *extra]},
        "minutes": {"geometry": round(geo_minutes, 1), "texture": round((t2 - t1) / 60, 1)},
        "figures": {"geometry": _figures(geo), "texture": _figures(tex)},
        **earlier,
    }
    if recipe["pose_steps"]:
        refit_pose(model, made, max(1, round(recipe["pose_steps"] * scale)), threads)
    return model, made


def _pose_only(species: str, source: Path, manifest_path: Path, threads: int) -> tuple[dict, dict]:
    """The pose stage alone on ``source`` (a file of the first two stages, whose manifest
    entry, if it is the shipped one, is carried over)."""
    steps = RECIPES[species]["pose_steps"]
    if not steps:
        raise SystemExit(f"{species}: the recipe has no pose stage (pose_steps 0)")
    if not source.is_file():
        raise SystemExit(f"--pose-from {source}: no such file")
    digest = sha256_file(source)
    entry = _manifest(manifest_path).get("models", {}).get(species, {})
    made = {k: v for k, v in entry.items()
            if k not in ("file", "sha256", "bytes", "torch", "machine", "commit", "date")}
    if entry.get("sha256") != digest:
        raise SystemExit(f"--pose-from {source}: not the file models.json records for "
                         f"{species} (sha256 {digest[:16]}...): retrain all stages instead")
    if "pose" in entry.get("steps", {}):
        raise SystemExit(f"--pose-from {source}: its pose code was refitted already (from "
                         f"{str(entry.get('pose_from_sha256'))[:16]}...)")
    model = load_checkpoint(source)
    refit_pose(model, made, steps, threads)
    made["pose_from_sha256"] = digest
    return model, made


def model_differences(retrained: dict, shipped: dict) -> list[str]:
    """What tells two stripped checkpoints apart, in words (empty: the same tensors and
    config): per module, the tensors that differ with their largest difference, those only in
    one of them, and the config keys (flattened) that differ or exist in one only."""

    lines = []
    for part in sorted(set(retrained["modules"]) | set(shipped["modules"])):
        a, b = retrained["modules"].get(part, {}), shipped["modules"].get(part, {})
        for name in sorted(set(a) ^ set(b)):
            lines.append(f"{part}.{name}: only in the {'retrained' if name in a else 'shipped'}")
        for name in sorted(set(a) & set(b)):
            x, y = a[name], b[name]
            if x.shape != y.shape:
                lines.append(f"{part}.{name}: shape {tuple(x.shape)} against {tuple(y.shape)}")
            elif not torch.equal(x, y):
                d = float((x.double() - y.double()).abs().max())
                lines.append(f"{part}.{name}: largest difference {d:.3g} "
                             f"(largest entry {float(y.double().abs().max()):.3g})")
    ca, cb = _flat(retrained["config"]), _flat(shipped["config"])
    for key in sorted(set(ca) | set(cb)):
        if key not in cb:
            lines.append(f"config {key}: only in the retrained ({ca[key]!r})")
        elif key not in ca:
            lines.append(f"config {key}: only in the shipped ({cb[key]!r})")
        elif ca[key] != cb[key]:
            lines.append(f"config {key}: {ca[key]!r} against {cb[key]!r}")
    if retrained.get("step") != shipped.get("step"):
        lines.append(f"step {retrained.get('step')} against {shipped.get('step')}")
    return lines


def _manifest(path: Path) -> dict:
    if path.is_file():
        return json.loads(path.read_text())
    return {"about": "NeTePu models shipped with the toolkit; made by "
                     "tools/train_species_models.py", "models": {}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("species", choices=sorted(RECIPES))
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads (default: the recipe's; another count gives another file)")
    ap.add_argument("--check", action="store_true",
                    help="train again and compare the SHA-256 with the shipped file's")
    ap.add_argument("--out", type=Path, default=MODELS, help="the models folder")
    ap.add_argument("--work", type=Path, default=None,
                    help="keep the two training runs here (default: a temporary folder)")
    ap.add_argument("--pose-from", type=Path, default=None,
                    help="only refit the pose code of this file (made by the first two stages)")
    ap.add_argument("--geometry-from", type=Path, default=None,
                    help="start at the texture stage from this earlier geometry run of the "
                         "recipe (an earlier --work folder's geometry/)")
    args = ap.parse_args(argv)
    if args.pose_from is not None and args.geometry_from is not None:
        ap.error("--pose-from and --geometry-from: one or the other")
    manifest_path = args.out / "models.json"
    with tempfile.TemporaryDirectory(prefix="species-models-") as tmp:
        threads = args.threads or RECIPES[args.species]["threads"]
        if args.pose_from is not None:
            model, made = _pose_only(args.species, args.pose_from, manifest_path, threads)
        else:
            model, made = train_species(args.species, args.work or Path(tmp), threads,
                                        geometry_from=args.geometry_from)
        target = Path(tmp) / f"{args.species}.pt" if args.check else args.out / f"{args.species}.pt"
        atomic_save_torch(model, target)
        digest = sha256_file(target)
        manifest = _manifest(manifest_path)  # read now: another species may have been written
        if args.check:
            shipped = manifest["models"].get(args.species, {}).get("sha256")
            same = digest == shipped
            print(f"{args.species}: retrained {digest}\n{'':>{len(args.species)}}  shipped  "
                  f"{shipped}\n{'bit for bit the same' if same else 'DIFFERENT'}")
            ours = args.out / f"{args.species}.pt"
            if not same and ours.is_file():  # say where: weights, or config keys added since
                for line in model_differences(model, torch.load(ours, weights_only=True)) or [
                        "the same tensors and config (another torch version wrote the file?)"]:
                    print(f"  {line}")
            return 0 if same else 1
    ship_file(manifest_path, manifest, "models", args.species, target, digest, made)
    return 0


if __name__ == "__main__":
    sys.exit(main())
