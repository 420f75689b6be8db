"""The masks' pixel ownership at inference: the hull's bonus x colour agreement on trained runs.

    .venv/bin/python tools/bench_ownership.py RUN [RUN ...]   # nsd-run output folders
    .venv/bin/python tools/bench_ownership.py RUN ... --hull-ownership 0 0.5 1 2 \
        --colour-sigma 0 0.2 0.4 --report ownership
    .venv/bin/python tools/bench_ownership.py RUN ... --hull-ownership 2 --colour-sigma 0.4 \
        --hull-contested 0 0.5 1 2 --report ownership_contested
    .venv/bin/python tools/bench_ownership.py RUN ... --hull-ownership 2 --colour-sigma 0.4 \
        --hull-contested 1 --colour-model 0 1 2 4 --colour-model-bins 8 16 \
        --report ownership_colour_models

The exported masks give every foreground pixel to the window with the largest ownership
score (:func:`nsd.inference.single.ownership`): the composited weight, the agreement of the
window's decoded colour with the pixel (``inference.colour_sigma``; 0: off) and, with
multi-view inference, a bonus for the window whose hull individual owns the pixel
(``inference.hull_ownership``; 0: the learned ownership alone), which is
``inference.hull_contested`` instead on the pixels near two or more hull individuals
(:func:`nsd.cues.occupancy.contested_pixels`), and the individuals' colour models add the
likelihood of the pixel's colour (``inference.colour_model``, ``.colour_model_bins``;
:mod:`nsd.inference.colour_models`). This script scores every combination on the
same checkpoints, so the defaults can be chosen on several scenes and training modes
together rather than on one (without ``--hull-contested``: the bonus is the same on every
pixel; without ``--colour-model``: the colour models off, as before they existed, so that
earlier ``--work`` folders stay valid).

For each run (a folder of ``nsd-run``: ``train/checkpoint.pt``, and the scene it was
trained on, from its ``scene/stage.json``) and each combination, ``nsd-eval`` scores the first
``--frames`` held-out frames; the hull-only decomposition (no learning) is scored once per
run on the same frames. Each ``nsd-eval`` runs on one thread, ``--jobs`` at a time; with
``--work`` the scores of an earlier call are reused.

Writes ``docs/benchmarks/<--report>.{md,json}``: one row per run and combination, then one
row per training mode (``model.mode``) and combination with the mean gain over the hull-only
row across that mode's runs (all frames and touching instants) and the worst run's gain.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.benchlib import write_report

BIN = Path(sys.executable).parent
NAN = float("nan")
KEEP = ("detection_rate", "mask_miou", "mask_miou_touching", "mask_miou_raw",
        "association_accuracy", "merge_rate", "touching_share")


def _scene(run: Path) -> str:
    stage = run / "scene" / "stage.json"
    if not stage.exists():
        raise SystemExit(f"{run}: not an nsd-run folder (no scene/stage.json)")
    return json.loads(stage.read_text())["summary"]["path"]


def _train_stage(run: Path) -> dict:
    """The run's ``train/stage.json``: its config and summary."""
    return json.loads((run / "train" / "stage.json").read_text())


def _training(stage: dict) -> str:
    """How a run's model was trained (its train stage): mode, steps, minutes, seed, windows."""
    cfg, summary = stage["config"], stage["summary"]
    return (f"{cfg['model']['mode']}, {summary.get('steps')} steps, "
            f"{cfg['trainer'].get('max_minutes')} minutes, seed {cfg['trainer'].get('seed')}, "
            f"{cfg['model']['num_windows']} windows")


def _eval(run: Path, out: Path, frames: int, overrides: list[str]) -> dict:
    if (out / "eval.json").exists():  # --work of an earlier call: scored already
        return json.loads((out / "eval.json").read_text())
    ckpt = run / "train" / "checkpoint.pt"
    if not ckpt.exists():
        raise SystemExit(f"{run}: no trained checkpoint ({ckpt})")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    done = subprocess.run(
        [str(BIN / "nsd-eval"), f"checkpoint={ckpt}", f"scene={_scene(run)}",
         f"max_frames={frames}", f"out={out}", "threads=1", *overrides],
        env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"nsd-eval failed on {run} {overrides}:\n{done.stderr[-2000:]}")
    return json.loads((out / "eval.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="nsd-run output folders")
    ap.add_argument("--hull-ownership", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0])
    ap.add_argument("--colour-sigma", type=float, nargs="+", default=[0.0, 0.2, 0.4])
    ap.add_argument("--hull-contested", type=float, nargs="*", default=[],
                    help="the bonus on contested pixels (default: --hull-ownership's)")
    ap.add_argument("--colour-model", type=float, nargs="*", default=[],
                    help="weights of the colour models (default: 0, off)")
    ap.add_argument("--colour-model-bins", type=int, nargs="*", default=[],
                    help="levels per colour channel of the colour models (default: the "
                         "config's)")
    ap.add_argument("--frames", type=int, default=30, help="held-out frames per run")
    ap.add_argument("--jobs", type=int, default=1, help="nsd-eval processes at a time")
    ap.add_argument("--label", nargs="*", default=[],
                    help="a name per run for the table (default: the folder's name)")
    ap.add_argument("--report", default="ownership", help="docs/benchmarks/<report>.{md,json}")
    ap.add_argument("--work", type=Path, default=None,
                    help="the folder of nsd-eval's outputs (default: a new temporary folder); "
                         "scores already in it are reused")
    args = ap.parse_args()
    if args.label and len(args.label) != len(args.runs):
        raise SystemExit(f"--label: {len(args.label)} names for {len(args.runs)} runs")
    labels = args.label or [r.name for r in args.runs]
    pairs = list(itertools.product(args.hull_ownership, args.colour_sigma,
                                   args.hull_contested or [None], args.colour_model or [0.0],
                                   args.colour_model_bins or [None]))
    # a weight of 0 is one setting whatever the bins
    pairs = [p for p in pairs if p[3] > 0 or p[4] == (args.colour_model_bins or [None])[0]]
    stages = [_train_stage(run) for run in args.runs]
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-ownership-"))
    jobs = [(i, run, None) for i, run in enumerate(args.runs)]  # the hull-only rows
    jobs += [(i, run, p) for i, run in enumerate(args.runs) for p in pairs]

    def one(job):
        i, run, pair = job
        if pair is None:
            m = _eval(run, work / f"{i}-hull", args.frames, ["baseline=true"])
            return job, {k: m.get(f"hull_{k}") for k in KEEP if f"hull_{k}" in m}
        h, c, hc, cm, bins = pair
        hc = h if hc is None else hc
        name = f"{i}-{h}-{c}" if hc == h else f"{i}-{h}-{c}-{hc}"  # earlier --work folders
        colour = [f"inference.colour_model={cm}"]
        if cm > 0:
            name += f"-cm{cm}" + ("" if bins is None else f"-{bins}")
            colour += [] if bins is None else [f"inference.colour_model_bins={bins}"]
        return job, _eval(run, work / name, args.frames,
                          ["baseline=false", f"inference.hull_ownership={h}",
                           f"inference.colour_sigma={c}", f"inference.hull_contested={hc}",
                           *colour])

    def contested(pair) -> dict:  # the columns exist where their setting was varied
        out = {}
        if args.hull_contested:
            out["hull_contested"] = "" if pair is None else pair[2]
        if args.colour_model:
            out["colour_model"] = "" if pair is None else pair[3]
        if args.colour_model_bins:
            out["colour_model_bins"] = "" if pair is None or not pair[3] else pair[4]
        return out

    with ThreadPoolExecutor(args.jobs) as pool:
        results = dict(pool.map(one, jobs))
    rows, gains = [], {}  # (training mode, pair) -> per run (mIoU, touching, detection) gains
    for i, run in enumerate(args.runs):
        hull, mode = results[(i, run, None)], stages[i]["config"]["model"]["mode"]
        rows.append({"run": labels[i], "hull_ownership": "hull-only", "colour_sigma": "",
                     **contested(None),
                     **{k: "" if k == "mask_miou_raw" else hull.get(k) for k in KEEP}})
        for p in pairs:
            m = results[(i, run, p)]
            rows.append({"run": labels[i], "hull_ownership": p[0], "colour_sigma": p[1],
                         **contested(p), **{k: m.get(k) for k in KEEP}})
            gains.setdefault((mode, p), []).append(
                (m["mask_miou"] - hull["mask_miou"],
                 m.get("mask_miou_touching", NAN) - hull.get("mask_miou_touching", NAN),
                 m["detection_rate"] - hull["detection_rate"]))
    for (mode, p), g in gains.items():
        touching = [x[1] for x in g if not math.isnan(x[1])]
        rows.append({"run": f"mean of {len(g)} {mode} runs", "hull_ownership": p[0],
                     "colour_sigma": p[1], **contested(p),
                     "mask_miou_gain": statistics.fmean(x[0] for x in g),
                     "mask_miou_gain_worst": min(x[0] for x in g),
                     "mask_miou_touching_gain": statistics.fmean(touching) if touching else None,
                     "detection_gain": statistics.fmean(x[2] for x in g)})
    notes = (f"`nsd-eval` on the first {args.frames} held-out frames of each run's scene, one "
             "thread. `hull-only`: the visual hull of the residuals alone on the same frames "
             "(nsd/evaluation/hull_baseline.py). Gains are the learned row minus the run's "
             "hull-only row; `mask_miou_gain_worst`: the run that gains least. Runs "
             "(`nsd-run` with `train.model.num_windows` = the scene's individuals): "
             + "; ".join(f"`{lab}`: {_training(st)}"
                         for lab, st in zip(labels, stages, strict=True)) + ".")
    write_report(args.report, "The masks' pixel ownership: the hull's bonus x colour agreement"
                 + (" x the individuals' colour models" if args.colour_model else ""),
                 rows, notes)


if __name__ == "__main__":
    main()
