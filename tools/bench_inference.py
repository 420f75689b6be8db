"""One inference setting, several values, on trained checkpoints: learned and hull-only rows.

    .venv/bin/python tools/bench_inference.py RUN [RUN ...] --label NAME ... \
        --key hole_share --values 0 0.02 0.04 0.08 --report holes
    .venv/bin/python tools/bench_inference.py RUN ... --key colour_model_separation \
        --values 0 0.1 0.2 0.3 --report colour_separation
    .venv/bin/python tools/bench_inference.py RUN ... --report detection_by_mask

For each run (an ``nsd-run`` folder with ``train/checkpoint.pt`` and the scene of its
``scene/stage.json``) and each of ``--values``, ``nsd-eval`` scores the trained checkpoint
with ``inference.<--key>=<value>`` (conf/inference/default.yaml; the other settings as
shipped; without ``--key``, the settings as shipped) on ``--frames`` frames of the
held-out tail: the learned decomposition and the hull-only row
(:mod:`nsd.evaluation.hull_baseline`), split apart / touching. Nothing is trained; the
runs' checkpoints are evaluated as they are, so a change of inference is measured on the
same models.

Reports made with it: ``holes`` (``hole_share``: the small holes a visible mask encloses
filled, :mod:`nsd.cues.holes`; made as ``tools/bench_holes.py``, this script's first
name), ``colour_separation`` (``colour_model_separation``: the colour models only in the
instants whose individuals they tell apart, :mod:`nsd.inference.colour_models`),
``islands`` (``island_share``: a subject's small islands inside another subject given to
it, :mod:`nsd.cues.holes`), ``neighbours`` (``neighbour_weight``: neighbouring pixels of one
colour drawn to one owner, :mod:`nsd.inference.neighbours`), ``slot_bonus`` (the hull
individual's weight in the cross-view association, :mod:`nsd.inference.association_scores`).

Writes ``docs/benchmarks/<--report>.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.benchlib import write_report

BIN = Path(sys.executable).parent
KEYS = ("detection_rate", "mask_detection_rate", "mask_miou", "mask_miou_touching",
        "detection_rate_touching", "mask_detection_rate_touching", "merge_rate",
        "association_accuracy")


NOTES = {  # what each setting does, for the report's notes
    "hole_share": "the holes a visible mask encloses, up to that share of its area, are "
                  "filled where no other subject shows (0: off; nsd/cues/holes.py); the "
                  "hull-only row's masks are filled the same way",
    "island_share": "a subject's islands (4-connected pieces other than its largest) that "
                    "one other subject encloses, up to that share of its area, are given to "
                    "that subject (0: off; nsd/cues/holes.py); the hull-only row's masks are "
                    "cleaned the same way",
    "neighbour_weight": "neighbouring pixels of one colour are drawn to one owner by a "
                        "contrast-sensitive Potts term on the mask ownership, between windows "
                        "as far as the colour models tell them apart (0: off; "
                        "nsd/inference/neighbours.py); the hull-only row has no ownership "
                        "scores and is unchanged",
    "slot_bonus": "association score added for the windows of two views fused with the same "
                  "visual-hull individual (0: appearance and geometry alone; "
                  "nsd/inference/association_scores.py); the hull-only row links views by the "
                  "hull individual itself and is unchanged",
    "colour_model_separation": "the individuals' colour models are used in an instant only "
                               "where their leave-one-out kappa reaches it (0: everywhere; "
                               "nsd/inference/colour_models.py); the hull-only row has no "
                               "colour models",
}


def _evaluate(run: Path, key: str | None, value: str, frames: int, out: Path,
              hull: bool) -> dict:
    """``nsd-eval``'s metrics of ``run``'s checkpoint with ``inference.<key>=<value>`` (the
    settings as shipped where ``key`` is None; the hull-only row's too where ``hull``)."""
    scene = json.loads((run / "scene" / "stage.json").read_text())["summary"]["path"]
    setting = [] if key is None else [f"inference.{key}={value}"]
    subprocess.run([str(BIN / "nsd-eval"), f"checkpoint={run / 'train' / 'checkpoint.pt'}",
                    f"scene={scene}", f"max_frames={frames}", *setting,
                    f"out={out}", f"baseline={str(hull).lower()}"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads((out / "eval.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="nsd-run folders")
    ap.add_argument("--label", nargs="+", default=None, help="a name per run (default: its folder)")
    ap.add_argument("--key", default=None,
                    help="an inference setting (conf/inference); none: score the settings as "
                         "shipped, once per run")
    ap.add_argument("--values", nargs="+", default=["shipped"],
                    help="its values, as nsd-eval reads them")
    ap.add_argument("--hull-once", action="store_true",
                    help="the setting does not change the hull-only row: score it once per run")
    ap.add_argument("--frames", type=int, default=30, help="held-out frames scored per run")
    ap.add_argument("--report", required=True, help="docs/benchmarks/<report>.{md,json}")
    args = ap.parse_args()
    if args.key is None and args.values != ["shipped"]:
        raise SystemExit("--values needs --key (without it the settings as shipped are scored)")
    labels = args.label or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        raise SystemExit("--label: one name per run")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-holes-") as tmp:
        for run, label in zip(args.runs, labels, strict=True):
            for i, value in enumerate(args.values):
                hull = not (args.hull_once and i)
                m = _evaluate(run, args.key, value, args.frames,
                              Path(tmp) / f"{run.name}-{value}", hull)
                for method, prefix in (("learned", ""), ("hull-only", "hull_"))[:1 + hull]:
                    row = {"run": label, "method": method}
                    if args.key is not None:
                        row[args.key] = (value if method == "learned" or not args.hull_once
                                         else "any")
                    row |= {"steps": m.get("step"), "touching_share": m.get("touching_share")}
                    row |= {key: m.get(prefix + key) for key in KEYS}
                    rows.append(row)
                    print(row, flush=True)
    setting = ("with the inference settings as shipped at the commit" if args.key is None else
               f"with `inference.{args.key}` = `{args.key}`: "
               f"{NOTES.get(args.key, 'conf/inference/default.yaml')}. The other settings as "
               "shipped at the commit")
    title = ("the shipped inference" if args.key is None else f"inference.{args.key}")
    write_report(
        args.report, f"{title} on trained checkpoints, learned and hull-only", rows,
        notes=(f"`tools/bench_inference.py{'' if args.key is None else ' --key ' + args.key}`: "
               f"`nsd-eval` of each run's trained checkpoint (`steps`: its training steps) on "
               f"{args.frames} frames of its scene's held-out tail {setting}. `learned`: the "
               "trained decomposition (multi-view inference); `hull-only`: the visual hull of "
               "the residuals alone. Metrics as "
               "nsd-eval's (nsd/evaluation/decomposition.py): detection by box IoU >= 0.5 "
               "after matching on mask IoU (`detection_rate`), detection by mask IoU >= 0.5 "
               "(`mask_detection_rate`), visible-mask mIoU, split apart / touching by "
               "nsd/evaluation/contact.py."))


if __name__ == "__main__":
    main()
