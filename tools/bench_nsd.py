"""NSD training benchmark: metrics after 5, 15 and 30 minutes, ablations, throughput, memory.

    python tools/bench_nsd.py main                  # default config, evals at 5/15/30 min
    python tools/bench_nsd.py ablations --minutes 15 --out DIR [--only NAME ...] [--report NAME]
    python tools/bench_nsd.py ablations_report --out DIR [--report NAME]
    python tools/bench_nsd.py ablations_inference --out DIR   # re-score with today's inference
    python tools/bench_nsd.py inference_speed --out RUN_DIR   # single-image vs multi-view
    python tools/bench_nsd.py collapse_report --runs "LABEL=RUN_DIR" ... [--at 9]
    python tools/bench_nsd.py throughput

Each configuration trains in a fresh subprocess (independent peak memory) on the
built-in default scene; figures go to ``docs/benchmarks/nsd_training.{md,json}``,
``nsd_ablations.{md,json}``, ``nsd_collapse.{md,json}`` and
``nsd_throughput.{md,json}``. Run one at a time: the machine has 2 cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.benchlib import markdown_table, write_report

KEYS = [
    "detection_rate",
    "mask_miou",
    "mask_miou_raw",
    "fg_ari",
    "depth_order_accuracy",
    "association_accuracy",
    "merge_rate",
    "overlap_ownership",
    "nvs_psnr",
    "nvs_ssim",
    "coco_bbox_ap",
    "coco_segm_ap",
]
TARGETS = {
    "detection_rate": 0.95,
    "mask_miou": 0.70,
    "depth_order_accuracy": 0.90,
    "association_accuracy": 0.95,
}

ABLATIONS = {
    "full (ours)": [],
    "full (ours), seed 1": ["trainer.seed=1"],
    "no weak priors": ["experiment=no_priors"],
    "classical ST": ["experiment=classical_st"],
    "no depth reasoning": ["experiment=no_depth"],
    "auto-encoder": ["model.mode=autoencoder"],
    "pixel loss only": ["experiment=pixel_only"],
    "NSD as published (no residual cues)": ["experiment=paper"],
    "no weak priors, seed 1": ["experiment=no_priors", "trainer.seed=1"],
    "full (ours), seed 2": ["trainer.seed=2"],
    "no priors of any kind": [
        "experiment=no_priors",
        "prior_proposal=off",
        "prior_depth=off",
        "prior_association=off",
    ],
    "upper bound 4, hull presence": [
        "model.num_windows=4",
        "model.detector.presence=true",
        "prior_presence=hull",
    ],
    "upper bound 2, hull presence": [
        "model.detector.presence=true",
        "prior_presence=hull",
    ],
    "half the pairs from the view itself": ["data.same_view=0.5"],
    "a quarter of the pairs from the view itself": ["data.same_view=0.25"],
    "a quarter of the pairs from the view itself, seed 1": [
        "data.same_view=0.25",
        "trainer.seed=1",
    ],
    "a quarter of the pairs from the view itself, seed 2": [
        "data.same_view=0.25",
        "trainer.seed=2",
    ],
    "a quarter of the pairs from the view itself, hull mask prior": [
        "data.same_view=0.25",
        "prior_mask=hull",
        "prior_mask.weight=1.0",
    ],
    "a quarter of the pairs from the view itself, hull mask prior x 4": [
        "data.same_view=0.25",
        "prior_mask=hull",
        "prior_mask.weight=4.0",
    ],
    "a quarter of the pairs from the view itself, hull mask prior x 4, 64 x 64 crops": [
        "data.same_view=0.25",
        "prior_mask=hull",
        "prior_mask.weight=4.0",
        "model.crop_size=64",
    ],
    "a quarter of the pairs from the view itself, mask refiner": [
        "data.same_view=0.25",
        "model.mask_refiner.widths=[16,32]",
        "model.mask_refiner.grow=null",
    ],
    "a quarter of the pairs from the view itself, mask refiner, seed 1": [
        "data.same_view=0.25",
        "model.mask_refiner.widths=[16,32]",
        "model.mask_refiner.grow=null",
        "trainer.seed=1",
    ],
    "a quarter of the pairs from the view itself, mask refiner, growth bounded": [
        "data.same_view=0.25",
        "model.mask_refiner.widths=[16,32]",
        "model.mask_refiner.grow=3.0",
    ],
    "a quarter of the pairs from the view itself, mask refiner, hull mask prior x 4": [
        "data.same_view=0.25",
        "model.mask_refiner.widths=[16,32]",
        "model.mask_refiner.grow=null",
        "prior_mask=hull",
        "prior_mask.weight=4.0",
    ],
    "a quarter of the pairs from the view itself, mask refiner, growth bounded, "
    "hull mask prior x 4": [
        "data.same_view=0.25",
        "model.mask_refiner.widths=[16,32]",
        "model.mask_refiner.grow=3.0",
        "prior_mask=hull",
        "prior_mask.weight=4.0",
    ],
}

# What a row was measured with unless it sets the key itself: the defaults of the time, pinned
# so that a later change of a default does not change the table (key prefix -> override).
PINNED = {
    "model.mode=": "model.mode=bi_nvs",  # the default until 2026-11-27
    "data.same_view=": "data.same_view=0",
    "prior_mask": "prior_mask=off",
    "model.mask_refiner": "model.mask_refiner.widths=[]",
}

CHILD = r"""
import json, resource, sys, torch
from hydra import compose, initialize_config_module
from pathlib import Path
from nsd.training.train import train
overrides = json.loads(sys.argv[1]); out = Path(sys.argv[2])
with initialize_config_module("nsd.conf", version_base="1.3"):
    cfg = compose("train", overrides=overrides)
metrics = train(cfg, out)
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print("RESULT " + json.dumps({"final": metrics, "peak_rss_mb": rss}))
"""


def train(overrides: list[str], out: Path) -> dict:
    """Train in a subprocess; returns its final metrics, evaluation history and peak RSS."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(overrides), str(out)],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not line:
        raise RuntimeError(f"training {overrides} failed:\n{proc.stderr[-3000:]}")
    res = json.loads(line[0][7:])
    history = []
    import csv

    with (out / "metrics.csv").open() as f:
        for row in csv.DictReader(f):
            if row.get("eval/mask_miou") not in (None, ""):
                history.append(
                    {
                        k.split("/", 1)[-1]: float(v)
                        for k, v in row.items()
                        if v not in (None, "")
                        and (k.startswith("eval/") or k in ("step", "minutes"))
                    }
                )
    res.update(history=history, wall_seconds=wall)
    return res


def _row(name: str, m: dict, minutes: float, steps: float) -> dict:
    row = {"setting": name, "minutes": round(minutes, 1), "steps": int(steps)}
    for k in KEYS:
        if k in m:
            row[k] = round(float(m[k]), 3)
    return row


def bench_main(minutes: list[float], out_root: Path) -> None:
    longest = max(minutes)
    marks = sorted(m for m in minutes if m < longest)
    res = train(
        [
            f"trainer.max_minutes={longest}",
            "trainer.max_steps=0",
            f"trainer.eval_at_minutes={marks}",
            "trainer.progress=false",
            "trainer.checkpoint_every=2000",
            "eval_train_frames=30",
        ],
        out_root / "main",
    )
    rows = []
    for where, frames in (("", "held-out frames"), ("train_", "training frames")):
        for how, inference in (("", "multi-view"), ("single_", "single-image")):
            prefix = where + how
            rows += [
                _row(
                    f"{frames}, {inference}",
                    {k[len(prefix) :]: v for k, v in h.items() if k.startswith(prefix)},
                    h["minutes"],
                    h["step"],
                )
                for h in res["history"]
            ]
    final = res["final"]
    notes = [
        "Default config (`nsd-train`), default synthetic scene (2 bipeds in close interaction, "
        "4 cameras, 128x128, 300 frames; the last 20 % held out), batch 8 view pairs, 2 cores. "
        "Evaluation on 30 held-out frames x 4 cameras (120 camera-frames, the sequence's last "
        "20 %, never trained on) and on 30 training frames (the transductive use: no labels are "
        "used in training, and users decompose the footage they trained on).",
        "",
        "Inference (`nsd/inference/multiview.py`, the `inference` config block): *multi-view* (the "
        "default) fuses each instant's detector windows with the label-free visual hull of its "
        "4 cameras (windows moved 3/4 of the way to their hull individual, depths from the "
        "hull, the hull's individual as an association term); *single-image* is NSD's own "
        "inference, each image alone. Both refine the masks with the background residual and "
        "the colour agreement of the decoded subjects (`inference.colour_sigma=0.2`).",
        "",
        "Targets at 15 minutes (issue): "
        + ", ".join(f"{k} >= {v}" for k, v in TARGETS.items())
        + ".",
    ]
    write_report(
        "nsd_training",
        "NSD / Bi-NVS training on the default scene",
        rows,
        "\n".join(notes),
        extra={
            "iterations_per_second": final.get("iterations_per_second"),
            "frames_per_second (2 views per pair x batch 8)": final.get("iterations_per_second", 0)
            * 16,
            "peak_rss_mb": res["peak_rss_mb"],
            "history": res["history"],
        },
    )


def _slug(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "")


def bench_ablations(minutes: float, out_root: Path, only: list[str] | None,
                    report: str = "nsd_ablations") -> None:
    """Train the named ablations (all by default) into ``out_root/<slug>/``.

    Each run leaves ``result.json``; the report is written from every result found
    in ``out_root``, so two processes (one per core, ``--only`` splitting the list,
    the same ``--out``) together produce one table.
    """
    for name, ov in ABLATIONS.items():
        if only and name not in only:
            continue
        out = out_root / _slug(name)
        ov = [pin for key, pin in PINNED.items() if not any(o.startswith(key) for o in ov)] + ov
        # ... and scored with single-image inference, no colour agreement (ablations_inference
        # re-scores the checkpoints with today's inference)
        ov = ["inference.views=single", "inference.colour_sigma=0", *ov]
        res = train(
            [
                *ov,
                f"trainer.max_minutes={minutes}",
                "trainer.max_steps=0",
                f"trainer.eval_at_minutes={[round(minutes * q / 5, 2) for q in (1, 2, 3, 4)]}",
                "trainer.progress=false",
                "trainer.checkpoint_every=0",
            ],
            out,
        )
        res["minutes"] = minutes
        tmp = out / "result.json.tmp"
        tmp.write_text(json.dumps(res))
        tmp.replace(out / "result.json")
    ablations_report(out_root, report)


def ablations_report(out_root: Path, report: str = "nsd_ablations") -> None:
    """The ablation table from the ``result.json`` files under ``out_root``."""
    rows, raw = [], {}
    for name in ABLATIONS:
        path = out_root / _slug(name) / "result.json"
        if not path.exists():
            continue
        res = json.loads(path.read_text())
        f, minutes = res["final"], res["minutes"]
        rows.append(_row(name, f, minutes, f.get("iterations_per_second", 0) * minutes * 60))
        rows[-1]["it_per_s"] = round(f.get("iterations_per_second", 0), 2)
        raw[name] = res
    if not rows:
        raise SystemExit(f"no ablation results under {out_root}")

    rescored = []
    for name in raw:
        path = out_root / _slug(name) / "inference.json"
        if path.exists():
            inf = json.loads(path.read_text())
            for views, label in (("multiview", "multi-view"), ("single", "single-image")):
                rescored.append(_row(f"{name}, {label}", inf[views], minutes, inf[views]["step"]))
            raw[name]["inference"] = inf
    rescored_md = (
        "\n\n## The same final checkpoints, re-scored with today's inference\n\n"
        "Multi-view: each instant's windows fused with the visual hull of its 4 cameras; "
        "single-image: NSD's own inference. Both with the colour agreement in the masks' "
        "ownership (`inference.colour_sigma=0.2`; the table above was scored without it, "
        "single-image). `python tools/bench_nsd.py ablations_inference --out DIR`.\n\n"
        + markdown_table(rescored)
        if rescored
        else ""
    )

    curve = []
    for name, res in raw.items():
        row = {"setting": name}
        for h in res["history"]:
            row[f"{h['minutes']:.0f} min"] = (
                f"{h.get('detection_rate', float('nan')):.2f} / {h['mask_miou']:.2f}"
                f" / {h.get('mask_miou_raw', float('nan')):.2f}"
            )
        curve.append(row)
    write_report(
        report,
        f"NSD ablations on the default scene ({minutes:g} min each)",
        rows,
        ("Each row changes one thing from the default config of the time, Bi-NVS pairs only "
         "(`data.same_view=0`, passed explicitly; see conf/experiment/). "
         if report == "nsd_ablations" else
         "Each row is the default config of the time with the overrides its name gives "
         "(`ABLATIONS` in tools/bench_nsd.py; rows that do not set `data.same_view` pass 0), "
         "scored with single-image inference and no colour agreement as in nsd_ablations.md. ")
        +
        "'NSD as published' removes our label-free background-residual cues (residual "
        "input and loss weight, foreground-evidence and proposal priors), the "
        "proposal depth and association priors and the geometric association term, and "
        "uses the reference code's mask max-normalisation. 'merge_rate': "
        "camera-frames where one window covers half of two subjects; "
        "'overlap_ownership': visible pixels of amodal overlaps given to their owner's "
        "window (nsd/evaluation/decomposition.py). Each run trained with 1 thread on its own core "
        "(the stamp gives the report process's threads)."
        "\n\n## Convergence (detection rate / mask mIoU / raw decoder mask mIoU)\n\n"
        + markdown_table(curve)
        + "\n\nHeld-out evaluations during training; minutes of training time, "
        "evaluation excluded." + rescored_md,
        extra={"runs": raw},
    )


def ablations_inference(out_root: Path, report: str = "nsd_ablations") -> None:
    """Re-score every ablation run's final checkpoint under ``out_root`` with multi-view and
    single-image inference (``<run>/inference.json``; the same 30 held-out frames as
    training's evaluations), then rewrite the report ``report``."""
    from nsd.evaluation.checkpoint import evaluate_checkpoint
    from nsd.inference.multiview import InferenceSettings

    for name in ABLATIONS:
        folder = out_root / _slug(name)
        if not (folder / "checkpoint.pt").exists() or (folder / "inference.json").exists():
            continue
        res = {}
        for views in ("multiview", "single"):
            m = evaluate_checkpoint(
                folder / "checkpoint.pt",
                None,
                "val",
                30,
                inference=InferenceSettings.defaults(views=views),
            )
            res[views] = {k: float(v) for k, v in m.items()}
        tmp = folder / "inference.json.tmp"
        tmp.write_text(json.dumps(res))
        tmp.replace(folder / "inference.json")
        print(name, {k: round(res["multiview"][k], 3) for k in TARGETS}, flush=True)
    ablations_report(out_root, report)


def inference_speed(checkpoint: Path, instants: int = 8, repeats: int = 5) -> None:
    """Seconds per instant (all 4 views) of single-image and multi-view inference, batches
    of ``instants`` held-out instants, median of ``repeats``; and their ratio."""
    import numpy as np
    import torch

    from nsd.inference.multiview import InferenceSettings, decompose_views
    from nsd.io.scene_data import SceneData
    from nsd.io.scenes import resolve_scene
    from nsd.model.checkpoint import load_decomposition
    from tools.benchlib import median_time

    torch.set_num_threads(2)
    trained = load_decomposition(checkpoint)
    cfg = trained.config
    H, W = trained.frame_hw
    data = SceneData(resolve_scene(cfg.data.scene), (W, H), cfg.data.cameras, cfg.data.val_fraction)
    V = data.num_views
    frames = np.asarray(data.val_frames)[:instants]
    views = torch.cat([data.views(int(t))[0] for t in frames])
    bgs = torch.cat([data.views(int(t))[1] for t in frames])
    rows, seconds = [], {}
    for views_mode in ("single", "multiview"):
        st = InferenceSettings.defaults(views=views_mode)
        grid = st.grid(data.rig, data.frame_hw) if st.multiview else None
        sec = median_time(
            lambda st=st, grid=grid: decompose_views(trained.model, views, bgs, V, st, grid),
            repeats,
        )
        seconds[views_mode] = sec / instants
        rows.append(
            {
                "inference": views_mode,
                "seconds per instant (4 views)": round(sec / instants, 4),
                "instants per second": round(instants / sec, 1),
                "camera-frames per second": round(instants * V / sec, 1),
            }
        )
    settings = InferenceSettings.defaults()
    grid_s = median_time(lambda: settings.grid(data.rig, data.frame_hw), repeats)
    write_report(
        "nsd_inference",
        "NSD inference speed: single-image and multi-view",
        rows,
        f"Default scene at 128x128, {instants} held-out instants of {V} views per call, "
        f"median of {repeats} calls, 2 threads, checkpoint `{checkpoint}`. Multi-view "
        "inference adds the visual hull of each instant (48^3 voxels) and the fusion; the "
        f"voxel grid itself is built once per footage ({grid_s:.2f} s). Multi-view / single "
        f"time ratio: {seconds['multiview'] / seconds['single']:.2f}.",
        extra={"ratio_multiview_to_single": seconds["multiview"] / seconds["single"]},
    )


def collapse_report(runs: list[str], at: float) -> None:
    """The held-out evaluation nearest to ``at`` minutes of each ``LABEL=RUN_DIR``.

    Reads each run's ``metrics.csv`` (nsd-train and the ablation runs write one), so runs
    trained at different commits can be set side by side; the labels say what differs.
    """
    import csv

    rows = []
    for spec in runs:
        label, _, folder = spec.partition("=")
        path = Path(folder) / "metrics.csv"
        if not folder or not path.is_file():
            raise SystemExit(f"--runs {spec!r}: expected LABEL=RUN_DIR with a metrics.csv")
        with path.open() as f:
            evals = [r for r in csv.DictReader(f) if r.get("eval/mask_miou")]
        if not evals:
            raise SystemExit(f"{path}: no evaluation rows")
        h = min(evals, key=lambda r: abs(float(r["minutes"]) - at))
        metrics = {k[5:]: float(v) for k, v in h.items() if k.startswith("eval/") and v}
        rows.append(_row(label, metrics, float(h["minutes"]), float(h["step"])))
    write_report(
        "nsd_collapse",
        f"NSD mask collapse: held-out figures after {at:g} minutes",
        rows,
        "Default scene, one thread on its own core per run (two runs at a time). "
        "`mask_miou_raw` scores the composited decoder masks without the residual "
        "refinement: 0 means the masks collapsed and the re-synthesis shows only the "
        "background. The labels name what differs from the default of the time; the "
        "old-default runs are the 15-minute ablation runs of commit 495c436, read at "
        "the same training time. docs/nsd.md interprets the table.",
        extra={"runs": runs, "at_minutes": at},
    )


def bench_throughput(out_root: Path) -> None:
    rows = []
    for name, ov in {
        "default (crop 32)": [],
        "crop 64": ["model.crop_size=64"],
        "batch 16": ["batch_size=16"],
    }.items():
        res = train(
            [
                *ov,
                "trainer.max_steps=150",
                "trainer.progress=false",
                "trainer.checkpoint_every=0",
                "eval_frames=2",
            ],
            out_root / name,
        )
        it = res["final"]["iterations_per_second"]
        bs = 16 if "batch 16" in name else 8
        rows.append(
            {
                "setting": name,
                "iterations_per_s": round(it, 2),
                "frames_per_s": round(it * bs * 2, 1),
                "peak_rss_mb": round(res["peak_rss_mb"], 0),
            }
        )
    write_report(
        "nsd_throughput",
        "NSD training throughput and peak memory",
        rows,
        "150 steps per setting after start-up; a frame is one view of a pair "
        "(each step reads 2 x batch frames). Peak RSS of the whole process, data "
        "(300 x 4 frames at 128x128) included.",
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "what",
        choices=[
            "main",
            "ablations",
            "ablations_report",
            "ablations_inference",
            "inference_speed",
            "collapse_report",
            "throughput",
        ],
    )
    ap.add_argument("--minutes", type=float, nargs="*", default=None)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--runs", nargs="*", default=[], help="LABEL=RUN_DIR (collapse_report)")
    ap.add_argument("--at", type=float, default=9.0, help="minutes (collapse_report)")
    ap.add_argument("--report", default="nsd_ablations",
                    help="report name (ablations, ablations_report): a subset of the rows "
                         "trained into their own --out goes to its own report")
    a = ap.parse_args()
    if a.what == "collapse_report":
        collapse_report(a.runs, a.at)
        return
    out = a.out or Path(tempfile.mkdtemp(prefix="bench_nsd_"))
    if a.what == "main":
        bench_main(a.minutes or [5, 15, 30], out)
    elif a.what == "ablations":
        bench_ablations((a.minutes or [15])[0], out, a.only, a.report)
    elif a.what == "ablations_report":
        ablations_report(out, a.report)
    elif a.what == "ablations_inference":
        ablations_inference(out, a.report)
    elif a.what == "inference_speed":
        inference_speed(a.out / "checkpoint.pt" if a.out.is_dir() else a.out)
    else:
        bench_throughput(out)
    print(out)


if __name__ == "__main__":
    main()
