"""Groups in contact: every decomposition metric split apart / touching, beside the hull-only row.

    .venv/bin/python tools/bench_contact.py          # ~40 minutes on 2 cores, nothing else running
    .venv/bin/python tools/bench_contact.py --seeds 0 1 --steps 3000  # two seeds, longer
    .venv/bin/python tools/bench_contact.py --minutes 15 --report contact_15min  # 15 minutes
    .venv/bin/python tools/bench_contact.py --minutes 15 --variants default auto-encoder \
        --report contact_ablations             # the paper's ablations, split apart / touching

For each scene (``nsd-synth motion.interaction=huddle``: the group alternates huddles, in
which every individual touches another, and dispersals), ``nsd-run`` trains with
``num_windows`` = the number of individuals for ``--steps`` steps (a step budget, so the
figures do not depend on the machine's load) or ``--minutes`` minutes of training (a time
budget: the steps it bought are in the ``train_steps`` column), evaluates on the held-out
tail and exports.
Rows per scene and seed:

* ``learned``: the trained decomposition (multi-view inference, the default);
* ``hull-only``: the visual hull of the background residuals alone on the same frames
  (:mod:`nsd.evaluation.hull_baseline`: no learning);
* with ``--variants``, one ``learned`` row per variant (``VARIANTS``: the paper's ablations
  as ``nsd-run`` overrides), beside one hull-only row per scene and seed (every variant is
  scored on the same frames, and the hull does not depend on the training).

Two halves of a long run can go side by side, one core each, into one folder
(``--root``, ``--train-only``: ``taskset -c 0 ... --variants default auto-encoder``,
``taskset -c 1 ... --variants "no depth reasoning" "no weak priors"``), then
``--rescore <root> --variants ...`` scores them all into one report.

``--checkpoints <root>`` trains nothing either: each run loads the trained checkpoint of the
same run in an earlier root (``nsd-run checkpoint=...``) and evaluates and exports it with
today's inference, so that a change of inference defaults is scored on the same models.

Writes ``docs/benchmarks/<--report>.{md,json}`` (default ``contact``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsd.evaluation.identity import identity_accuracy_by_contact
from nsd.io.identities import read_identities
from tools.benchlib import write_report

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SCENES = {  # name -> (individuals, nsd-synth overrides)
    "2 bipeds, 4 cameras": (2, ["num_individuals=2"]),
    "3 bipeds, 4 cameras": (3, ["num_individuals=3"]),
    "4 (bipeds, quadrupeds), 8 cameras": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0"]),
    "6 bipeds, 8 cameras": (6, ["num_individuals=6", "rig.count=8", "motion.area_radius=2.0"]),
}


def _mixed(n: int, species: str, radius: float, seed: int) -> tuple[int, list[str]]:
    """A scene of both species of bench_hull.py's list (its nsd-synth overrides and seed)."""
    return n, [f"num_individuals={n}", f"species=[{species}]", "rig.count=8",
               f"motion.area_radius={radius}", f"seed={seed}"]


SCENES |= {
    "3 (2 quadrupeds, 1 biped), 8 cameras, seed 11": _mixed(3, "quadruped,biped", 2.5, 11),
    "5 (bipeds, quadrupeds), 8 cameras, seed 12": _mixed(5, "biped,quadruped", 3.0, 12),
    # the two scenes bench_hull.py made after its mixture rules were chosen
    "4 (bipeds, quadrupeds), 8 cameras, seed 21": _mixed(4, "biped,quadruped", 2.0, 21),
    "6 (bipeds, quadrupeds), 8 cameras, seed 22": _mixed(6, "biped,quadruped", 3.0, 22),
    # textures 1 and 11 are a look-alike pair of the pool (nsd/synth/texture.py)
    "3 bipeds, two of them look-alikes, 4 cameras": (
        3, ["num_individuals=3", "texture_ids=[1,11,7]"]),
    # one texture for all three: only where they stand tells them apart (mice of one strain)
    "3 bipeds of one texture, 4 cameras": (3, ["num_individuals=3", "texture_ids=[1,1,1]"]),
    # made after method=motion was chosen on the one above: another texture, another seed
    "4 bipeds of one texture, 4 cameras, seed 2": (
        4, ["num_individuals=4", "texture_ids=[7,7,7,7]", "seed=2"]),
    "3 bipeds of one texture, 4 cameras, seed 3": (
        3, ["num_individuals=3", "texture_ids=[11,11,11]", "seed=3"]),
    # quadrupeds that look alike (cattle of one breed; a pair, as mice are most often filmed)
    "2 quadrupeds of one texture, 4 cameras, seed 4": (
        2, ["num_individuals=2", "species=[quadruped]", "texture_ids=[6,6]", "seed=4"]),
    "3 quadrupeds of one texture, 4 cameras, seed 5": (
        3, ["num_individuals=3", "species=[quadruped]", "texture_ids=[6,6,6]",
            "motion.area_radius=2.0", "seed=5"]),
    # made after inference.colour_model_separation was chosen: one texture for all, and two
    # pairs (a look-alike pair and one texture twice)
    "3 bipeds of one texture, 4 cameras, seed 6": (
        3, ["num_individuals=3", "texture_ids=[4,4,4]", "seed=6"]),
    "4 bipeds, a look-alike pair and a pair of one texture, 4 cameras, seed 7": (
        4, ["num_individuals=4", "texture_ids=[1,11,7,7]", "seed=7"]),
    # made after colour_model_separation became a rule between pairs of individuals
    "3 bipeds, a pair of one texture and another, 4 cameras, seed 8": (
        3, ["num_individuals=3", "texture_ids=[9,9,2]", "seed=8"]),
    # made for issue 26's keypoints of three individuals: three quadrupeds that look different
    "3 quadrupeds, 4 cameras, seed 9": (
        3, ["num_individuals=3", "species=[quadruped]", "motion.area_radius=2.0", "seed=9"]),
    # made on 2026-11-30 after every setting of today's defaults was chosen: blind checks
    "4 (bipeds, quadrupeds), 8 cameras, seed 23": _mixed(4, "biped,quadruped", 2.0, 23),
    "3 bipeds, 4 cameras, seed 24": (3, ["num_individuals=3", "seed=24"]),
}
BI_NVS = ["train.model.mode=bi_nvs"]  # the default training until 2026-11-27
VARIANTS = {  # name -> nsd-run overrides (the ablations of tools/bench_nsd.py, on nsd-run)
    "default": [],  # nsd-run's defaults: the auto-encoder since 2026-11-27
    "Bi-NVS": BI_NVS,  # with a quarter of the pairs from the view itself (data.same_view)
    "Bi-NVS only": [*BI_NVS, "train.data.same_view=0"],  # every pair across views, as the paper
    "half the pairs from the view itself": [*BI_NVS, "train.data.same_view=0.5"],
    "auto-encoder": ["train.model.mode=autoencoder"],
    # the paper's other ablations, on Bi-NVS as they were measured
    "no depth reasoning": [*BI_NVS, "train.model.depth=false"],
    "no weak priors": [*BI_NVS, *(f"{p}@train.{p}=off"
                                  for p in ("prior_position", "prior_scale", "prior_aspect"))],
    "mask refiner + hull mask prior": [*BI_NVS, "train.model.mask_refiner.widths=[16,32]",
                                       "prior_mask@train.prior_mask=hull",
                                       "train.prior_mask.weight=4"],
}
METRICS = ("detection_rate", "mask_detection_rate", "mask_miou", "depth_order_accuracy",
           "association_accuracy", "merge_rate")
PARTS = ("", "_apart", "_touching")


def _row(scene: str, seed: int, method: str, m: dict, prefix: str = "") -> dict:
    row = {"scene": scene, "seed": seed, "method": method,
           "touching_share": m.get(f"{prefix}touching_share")}
    for key in METRICS:
        for part in PARTS:
            row[f"{key}{part or '_all'}"] = m.get(f"{prefix}{key}{part}")
    return row


def _identity_split(out: Path, scene: Path) -> dict:
    """Identity accuracy of the run's identities, all rows and split apart / touching (the
    identities stage's own figures; recomputed here for runs made before it split them)."""
    ids = read_identities(out / "identities" / "identities.csv")
    keep = ids["identity"] >= 0
    rows = {k: v[keep] for k, v in ids.items()}
    return identity_accuracy_by_contact(out / "export", scene, rows, rows["identity"], (128, 128))


def _identities_from(rec: dict) -> str:
    """What the run's identities were computed from: texture codes (of which species'
    models) or NSD's appearance vectors."""
    ident = rec["identities"]["summary"]
    if ident.get("column") == "app":
        return "NSD appearance vectors"
    species = sorted(ident.get("species", {}))
    return "texture codes" + (f" within each species ({', '.join(species)})" if species else "")


def _carried(scenes: list[str], report: str) -> list[dict]:
    """The rows of ``scenes`` in the current docs/benchmarks/<report>.json, marked with their
    date and commit (a scene not re-run this time keeps its figures, visibly older)."""
    if not scenes:
        return []
    old = json.loads((ROOT / "docs" / "benchmarks" / f"{report}.json").read_text())
    rows = [dict(r, measured=r["measured"] if r.get("measured", "this run") != "this run"
                 else f"{old['date']}, `{old['commit']}`")  # a row carried before keeps its date
            for r in old["rows"] if r["scene"] in scenes]
    missing = set(scenes) - {r["scene"] for r in rows}
    if missing:
        raise SystemExit(f"--carry: no rows of {sorted(missing)} in {report}.json")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1000, help="training steps per scene")
    ap.add_argument("--minutes", type=float, default=0.0,
                    help="a time budget per scene instead of --steps (0: the step budget)")
    ap.add_argument("--report", default="contact", help="docs/benchmarks/<report>.{md,json}")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES),
                    help="scene names to run")
    ap.add_argument("--rescore", type=Path, default=None,
                    help="a folder of an earlier run of this script: score it, train nothing")
    ap.add_argument("--carry", nargs="*", default=[],
                    help="scene names whose rows are kept from the report being replaced, "
                         "marked with when and at which commit they were measured")
    ap.add_argument("--variants", nargs="+", default=["default"], choices=list(VARIANTS),
                    help="training variants per scene and seed (VARIANTS)")
    ap.add_argument("--root", type=Path, default=None,
                    help="the folder of scenes and runs (default: a new temporary folder); "
                         "scenes already in it are not generated again")
    ap.add_argument("--checkpoints", type=Path, default=None,
                    help="an earlier root whose runs' checkpoints are loaded instead of training")
    ap.add_argument("--note", default="",
                    help="a sentence appended to the report's notes (e.g. how its runs were made)")
    ap.add_argument("--train-only", action="store_true",
                    help="train and export, score nothing, write no report (see --rescore)")
    args = ap.parse_args()
    carried = _carried(args.carry, args.report)
    budget = ([f"train.trainer.max_steps={args.steps}", "train.trainer.max_minutes=0"]
              if args.minutes <= 0 else
              ["train.trainer.max_steps=0", f"train.trainer.max_minutes={args.minutes}"])
    root = args.rescore or args.root or Path(tempfile.mkdtemp(prefix="bench-contact-"))
    rows = []
    for name in args.scenes:
        i = list(SCENES).index(name)  # scene<i> is the same scene whichever --scenes are run
        n, synth = SCENES[name]
        scene = root / f"scene{i}"
        if not args.rescore and not (scene / "calibration.toml").exists():
            seed = [] if any(o.startswith("seed=") for o in synth) else ["seed=1"]
            subprocess.run([str(BIN / "nsd-synth"), f"out={scene}", "motion.interaction=huddle",
                            *seed, *synth], check=True, capture_output=True)
        for seed, variant in [(s, v) for s in args.seeds for v in args.variants]:
            slug = "" if variant == "default" else "-" + variant.replace(" ", "_")
            out = root / f"run{i}-{seed}{slug}"
            if args.rescore and not (out / "pipeline.json").exists():
                continue  # --rescore: the seeds and variants that were run
            if args.checkpoints and not args.rescore:
                ckpt = args.checkpoints / out.name / "train" / "checkpoint.pt"
                if not ckpt.is_file():
                    raise SystemExit(f"--checkpoints: no {ckpt}")
                trained = [f"checkpoint={ckpt}"]
            else:
                trained = [f"train.trainer.seed={seed}", *budget]
            if not args.rescore:
                subprocess.run(
                    [str(BIN / "nsd-run"), f"scene={scene}", f"out={out}",
                     f"train.model.num_windows={n}", *trained, *VARIANTS[variant],
                     "evaluate.max_frames=30", "grids.frames=0", "overlays.enabled=false"],
                    check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            if args.train_only:
                continue
            rec = json.loads((out / "pipeline.json").read_text())
            m = rec["evaluate"]["summary"]["metrics"]
            ident = rec["identities"]["summary"]
            method = "learned" if variant == "default" else f"learned, {variant}"
            learned = _row(name, seed, method, m)
            learned["mask_miou_raw_all"] = m.get("mask_miou_raw")
            split = _identity_split(out, scene)
            for part in PARTS:
                learned[f"identity_accuracy{part or '_all'}"] = split.get(
                    f"identity_accuracy{part}")
            learned["idf1"] = ident.get("tracking", {}).get("identities", {}).get("idf1")
            chosen = (f"auto: {ident['method']} (code separation {ident['separation']:.2f})"
                      if ident.get("chosen_by") == "auto" else ident.get("method", "rows"))
            learned["identities"] = (f"{chosen}, "
                                     f"fill {ident.get('fill', 'tracks')}, "
                                     f"{_identities_from(rec)}")
            # rows of a camera-frame that share their identity with another (the pose tools'
            # files keep one of them): at most one of them can be right
            learned["shared_identity_rows"] = rec.get("formats", {}).get("summary", {}).get(
                "rows_left_out", 0)
            kp = rec.get("keypoints", {}).get("summary", {})
            learned["species_accuracy"] = kp.get("species_accuracy", {}).get("accuracy")
            learned["train_steps"] = rec["train"]["summary"].get("steps")
            rows.append(learned)
            if not any(r["method"] == "hull-only" and r["scene"] == name and r["seed"] == seed
                       for r in rows):  # the same frames in every variant: one hull row
                rows.append(_row(name, seed, "hull-only", m, "hull_"))
            print(rows[-1], flush=True)
    if args.train_only:
        return
    for r in rows:
        r["measured"] = "this run"
    rows += carried
    budget_text = (f"`train.trainer.max_steps={args.steps}`" if args.minutes <= 0 else
                   f"`train.trainer.max_minutes={args.minutes:g}` (steps bought: `train_steps`)")
    if args.checkpoints:
        budget_text += (" (trained earlier, then loaded with `nsd-run checkpoint=...` and "
                        "evaluated and exported with this commit's inference)")
    write_report(
        args.report, "Groups in contact: metrics apart / touching, learned and hull-only", rows,
        notes=(f"`nsd-run` per scene and seed with `train.model.num_windows` = the number of "
               f"individuals, {budget_text}, evaluated on 30 frames "
               "of the held-out tail (nsd-eval's metrics, nsd/evaluation/decomposition.py), "
               "split by nsd/evaluation/contact.py: an instant is touching when two "
               "individuals' amodal masks overlap in most cameras that see both. Scenes: "
               "`nsd-synth motion.interaction=huddle seed=1` (or the seed the scene names). "
               "`hull-only`: the visual hull "
               "of the residuals alone (nsd/evaluation/hull_baseline.py). Identity accuracy "
               "and IDF1 (whole export, all frames, split apart / touching by frame) exist for the "
               "learned rows only: the hull-only decomposition has no identities over time; "
               "`identities`: how they were assigned (`netepu.identities.method`, `.fill`, and "
               "from what). `species_accuracy`: in scenes of two species, the share of "
               "inverted subject-frames that took the species of the individual they match "
               "(netepu/pipeline/species_choice.py). `shared_identity_rows`: rows of the "
               "export whose camera-frame holds another row of their identity (at most one "
               "of them can be right). "
               "`measured`: this run, or the date and commit of rows carried from an "
               "earlier report (`--carry`: scenes not re-run)." + (f" {args.note}" if args.note
                                                                    else "")),
    )


if __name__ == "__main__":
    main()
