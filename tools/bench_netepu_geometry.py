"""Benchmark of the NeTePu geometry renderer: accuracy, FLOPs per pixel, render and training speed.

Writes ``docs/benchmarks/netepu_geometry.md`` and ``.json`` (:func:`tools.benchlib.write_report`).

Sections
    accuracy: silhouette IoU, NNOPCS MSE and depth MAE of trained checkpoints on
        held-out poses (training cameras) and held-out poses seen by held-out
        cameras, rendered coarse-to-fine and per pixel (culled), plus the
        learning curve of each run (its ``metrics.csv``).
    cost: FLOPs per query pixel (``torch.utils.flop_counter.FlopCounterMode``)
        and per image pixel of full renders, and milliseconds per 128 x 128 and
        256 x 256 render, for our model and the NePu-size reference
        (``conf/netepu/model/reference.yaml``) in the same process.
    training: step time and peak memory (RSS) per configuration, each in a
        fresh subprocess.

Usage (on an otherwise idle machine; takes ~10 minutes)::

    .venv/bin/python tools/bench_netepu_geometry.py --data biped \\
        --run ours=runs/netepu/geometry_biped --run reference=runs/netepu/biped_reference
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netepu.geometry.data import build_geometry_data, sample_batch  # noqa: E402
from netepu.geometry.evaluation import body_length, evaluate_views  # noqa: E402
from netepu.geometry.maps import MapSettings, render_maps  # noqa: E402
from netepu.geometry.model import build_geometry_model, load_geometry_model  # noqa: E402
from tools.benchlib import (  # noqa: E402
    evaluations,
    markdown_table,
    median_time,
    peak_rss_mb,
    write_report,
)

PAPER = {"nnopcs_mse": 1.6e-4, "depth_mae_mm": 17.8, "body_length_m": 2.2}
REFERENCE_NOTES = {"mflops_per_pixel": 12.2, "ms_128": 3100.0}


def _config(overrides: list[str]):
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose("netepu_train", overrides=overrides)
    return OmegaConf.to_container(cfg, resolve=True)


# ------------------------------------------------------------------ accuracy
def accuracy(
    runs: dict[str, Path], data, slow_views: int, light: bool = False
) -> tuple[list[dict], dict]:
    rows, curves = [], {}
    body = body_length(data.evaluation["heldout_poses"].keypoints, data.config.species)
    for name, run in runs.items():
        model, config = load_geometry_model(run / "checkpoint.pt")
        state = torch.load(run / "checkpoint.pt", weights_only=True, map_location="cpu")
        minutes = state["train_seconds"] / 60
        slow = model.renderer.vca.mode == "reference"  # seconds per render: a subset only
        # every model on the reference's subset (same views), fast models on all views too
        passes = (
            [("coarse_to_fine", True)]
            if slow
            else [("coarse_to_fine", True), ("culled", True)]
            if light
            else [("coarse_to_fine", False), ("culled", False), ("coarse_to_fine", True)]
        )
        for mode, subset in passes:
            settings = MapSettings.from_config({**config["netepu"]["render"], "mode": mode})
            for set_name in ("heldout_poses", "heldout_cameras", "train"):
                views = data.evaluation[set_name]
                if subset:
                    n = min(slow_views, len(views))
                    views = views.subset(np.linspace(0, len(views) - 1, n).round().astype(int))
                t0 = time.perf_counter()
                m = evaluate_views(model, views, settings)
                rows.append(
                    {
                        "model": name,
                        "steps": int(state["step"]),
                        "train_min": round(minutes, 1),
                        "render": mode,
                        "views": f"{set_name} ({len(views)}{' subset' if subset else ''})",
                        "IoU": m["iou"],
                        "NNOPCS MSE": m["nnopcs_mse"],
                        "depth MAE mm": m["depth_mae_mm"],
                        "depth MAE % body": 100 * m["depth_mae_mm"] / 1000 / body,
                        "evals/pixel": m["evaluations_per_pixel"],
                        "coverage": m["coverage"],
                        "eval s": time.perf_counter() - t0,
                    }
                )
                print(rows[-1], flush=True)
        if (run / "metrics.csv").is_file():
            curves[name] = [
                {k: v for k, v in r.items()
                 if v not in ("", None) and (k in ("step", "minutes") or k.startswith("eval/"))}
                for r in evaluations(run)
            ]
    return rows, {"body_length_m": body, "curves": curves}


# ------------------------------------------------------------------ cost
def _square_rig_views(data, size: int, n: int = 4):
    """Held-out poses seen by the training rig's cameras at size x size (same field of view)."""
    from netepu.geometry.data import _make_rig  # the data module's rig builder

    views = data.evaluation["heldout_poses"]
    rig = _make_rig(data.config.rig, (size, size))
    cams = rig.stacked(torch.float32)
    idx = torch.arange(n) * 3 % len(rig)
    return views.keypoints[:n], cams[idx]


def _flops(fn) -> int:
    with FlopCounterMode(display=False) as fc:
        fn()
    return fc.get_total_flops()


def _full_render(model, keypoints, camera, size: int, settings: MapSettings):
    """Everything a full render of one view costs: encode, prepare, render the maps."""
    code = model.encode(keypoints)
    ctx = model.prepare(code, camera, keypoints=keypoints)
    return render_maps(model.query, ctx, (size, size), settings)


def _prepare(model, keypoints, camera):
    """The per-view part of a render: encode and prepare."""
    return model.prepare(model.encode(keypoints), camera, keypoints=keypoints)


def _query_flops(model, keypoints, camera, size: int, n: int = 4096) -> float:
    """FLOPs of one network evaluation at one pixel (per-view precomputation excluded)."""
    ctx = model.prepare(model.encode(keypoints), camera, keypoints=keypoints)
    uv = torch.rand(1, n, 2) * size
    return _flops(partial(model.query, ctx, uv)) / n


@torch.no_grad()
def cost(models: dict[str, torch.nn.Module], data, quick: bool, light: bool = False) -> list[dict]:
    """FLOPs and times of full renders. ``light``: one view, no timings, and the
    reference's dense render counted as its per-view part plus pixels x FLOPs per query
    (what a dense render evaluates) instead of running it."""
    rows = []
    for name, model in models.items():
        model.eval()
        is_ref = model.renderer.vca.mode == "reference"
        for size in (128, 256):
            kps, cams = _square_rig_views(data, size, n=1 if (is_ref or light) else 4)
            nq = 256 if light else 4096
            q = _query_flops(model, kps[:1], cams[:1], size, nq)
            for mode in ["dense"] if is_ref else ["dense", "culled", "coarse_to_fine"]:
                settings = MapSettings.defaults(mode=mode, margin=0.35)
                per_view = []
                for v in range(kps.shape[0]):
                    cam = cams[v : v + 1]
                    render = partial(_full_render, model, kps[v : v + 1], cam, size, settings)
                    if light and is_ref:  # dense: every pixel once, plus the per-view part
                        per_view_part = _flops(partial(_prepare, model, kps[v : v + 1], cam))
                        per_view.append(
                            (per_view_part + q * size**2, float("nan"), size**2, float("nan"))
                        )
                        continue
                    flops = _flops(render)
                    maps = render()
                    if light:
                        t = float("nan")
                    elif is_ref and size == 256 and quick:
                        t = float("nan")
                    else:
                        t = median_time(
                            render, repeats=1 if (is_ref or quick) else 5, warmup=0 if is_ref else 1
                        )
                    per_view.append(
                        (flops, t, int(maps.evaluated[0]), float(maps.silhouette.float().mean()))
                    )
                f, t, ev, fg = (float(np.mean([p[i] for p in per_view])) for i in range(4))
                rows.append(
                    {
                        "model": name,
                        "size": f"{size}x{size}",
                        "render": mode,
                        "MFLOPs/query": q / 1e6,
                        "MFLOPs/image pixel": f / size**2 / 1e6,
                        "evals/pixel": ev / size**2,
                        "fg share": fg,
                        "ms/render": 1000 * t,
                        "views": len(per_view),
                    }
                )
                print(rows[-1], flush=True)
    return rows


# ------------------------------------------------------------------ training
def train_step_child(model_name: str, batch: int, steps: int, species: str) -> dict:
    """Run in a fresh process: median step time and peak RSS of training at ``batch``."""
    from netepu.geometry.losses import GeometryLossWeights
    from netepu.geometry.stage import GeometryStageConfig, GeometryTask

    cfg = _config([f"netepu/model={model_name}", f"netepu/data={species}"])
    net = cfg["netepu"]
    data = build_geometry_data(net["data"])
    rss0 = peak_rss_mb()
    torch.manual_seed(0)
    model = build_geometry_model(net["model"], data.config.n_keypoints, data.config.radius)
    stage = GeometryStageConfig.from_mapping(
        {**net["optim"], "batch_size": batch}, net["points"], net["eval"]
    )
    weights = GeometryLossWeights.from_config(net["loss"])
    task = GeometryTask(model, data, stage, weights, MapSettings.defaults())
    rng = np.random.default_rng(0)

    def step():  # what nsd.core.trainer.Trainer does per step
        opts = task.optimizers().values()
        for o in opts:
            o.zero_grad()
        loss = task.losses(
            sample_batch(data, rng, batch, stage.near, stage.far, stage.foreground), rng
        )["loss"]
        loss.backward()
        for o in opts:
            torch.nn.utils.clip_grad_norm_([p for g in o.param_groups for p in g["params"]], 1.0)
            o.step()

    t = median_time(step, repeats=steps, warmup=1)
    return {
        "model": model_name,
        "batch": batch,
        "step s": t,
        "views/s": batch / t,
        "peak RSS MiB": peak_rss_mb(),
        "RSS over data MiB": peak_rss_mb() - rss0,
        "params M": sum(p.numel() for p in model.parameters()) / 1e6,
    }


def training(configs: list[tuple[str, int, int]], species: str) -> list[dict]:
    rows = []
    for model_name, batch, steps in configs:
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--train-step-child",
                model_name,
                str(batch),
                str(steps),
                species,
                "--threads",
                str(torch.get_num_threads()),
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        if out.returncode != 0:
            rows.append(
                {
                    "model": model_name,
                    "batch": batch,
                    "error": out.stderr.strip().splitlines()[-1][:120],
                }
            )
        else:
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(rows[-1], flush=True)
    return rows


# ------------------------------------------------------------------ report
def _equal_steps(curve: list[dict]) -> list[dict]:
    """Rows of the reference run's curve, each with our curve's row at the nearest step."""
    ours = [r for r in curve if r["model"] != "reference"]  # every run of our model
    rows = []
    for r in (r for r in curve if r["model"] == "reference"):
        if not ours:
            break
        near = min(ours, key=lambda o: abs(int(o["step"]) - int(r["step"])))
        rows += [r, near]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", default=[], help="name=run_dir of a trained model")
    ap.add_argument("--quick", action="store_true", help="fewer repeats (smoke test)")
    ap.add_argument("--skip-training", action="store_true")
    ap.add_argument(
        "--slow-views",
        type=int,
        default=24,
        help="views per evaluation set for reference-size models",
    )
    ap.add_argument(
        "--data", default="quadruped", help="netepu/data config of the runs (quadruped | biped)"
    )
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the timings")
    ap.add_argument(
        "--light",
        action="store_true",
        help="FLOPs and accuracy on the --slow-views subsets only: no timings, no training",
    )
    ap.add_argument("--train-step-child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.train_step_child:
        name, batch, steps, species = args.train_step_child
        print(json.dumps(train_step_child(name, int(batch), int(steps), species)))
        return
    cfg = _config([f"netepu/data={args.data}"])
    data = build_geometry_data(cfg["netepu"]["data"])
    runs = {n: ROOT / p for n, p in (r.split("=", 1) for r in args.run)}
    acc_rows, acc_extra = accuracy(runs, data, args.slow_views, args.light) if runs else ([], {})

    models = {}
    if "ours" in runs:
        models["ours (trained)"] = load_geometry_model(runs["ours"] / "checkpoint.pt")[0]
    else:
        torch.manual_seed(0)
        models["ours (untrained)"] = build_geometry_model(
            cfg["netepu"]["model"], data.config.n_keypoints, data.config.radius
        )
    torch.manual_seed(0)
    ref_cfg = _config(["netepu/model=reference", f"netepu/data={args.data}"])["netepu"]["model"]
    models["reference size"] = build_geometry_model(
        ref_cfg, data.config.n_keypoints, data.config.radius
    )
    cost_rows = cost(models, data, args.quick, args.light)
    train_rows = (
        []
        if args.skip_training
        else training(
            [("fast", 16, 10), ("fast", 64, 5), ("reference", 1, 3), ("reference", 4, 2)], args.data
        )
    )

    ours = {(r["size"], r["render"]): r for r in cost_rows if r["model"].startswith("ours")}
    ref = {r["size"]: r for r in cost_rows if r["model"] == "reference size"}
    ratios = {}
    for (size, mode), r in ours.items():
        if size in ref:
            ratios[f"{size} {mode}: FLOPs/pixel ratio"] = (
                ref[size]["MFLOPs/image pixel"] / r["MFLOPs/image pixel"]
            )
            if np.isfinite(ref[size]["ms/render"]) and np.isfinite(r["ms/render"]):
                ratios[f"{size} {mode}: time ratio"] = ref[size]["ms/render"] / r["ms/render"]
    ratios["FLOPs per query ratio"] = (
        ref["128x128"]["MFLOPs/query"] / ours[("128x128", "dense")]["MFLOPs/query"]
    )
    notes = "\n\n".join(
        [
            "## Accuracy\n\nRendered from the ground-truth keypoints of each view. NNOPCS MSE and "
            "depth MAE over pixels foreground in both ground truth and render. `coarse_to_fine` is "
            "the default renderer; `culled` evaluates every pixel of the candidate region (what "
            "coarse-to-fine approximates). Paper (NeTePu table 1, NePuMoo, full training on a "
            "GPU): "
            f"NNOPCS MSE {PAPER['nnopcs_mse']:.1e}, depth MAE {PAPER['depth_mae_mm']} mm on a "
            f"{PAPER['body_length_m']} m cow ({100 * PAPER['depth_mae_mm'] / 2200:.2f} % of its "
            f"length). Data: `netepu/data={args.data}`, body size "
            f"{acc_extra.get('body_length_m', float('nan')):.2f} m (keypoint extent: length of "
            "a quadruped, height of a biped); `depth MAE % body` divides by it.",
            "## Cost per pixel and render time\n\n"
            + markdown_table(cost_rows)
            + "\n\nFLOPs are what `FlopCounterMode` counts (matrix products; element-wise maths "
            "such as sin/cos/exp is not counted, for both models alike). `MFLOPs/query` is one "
            "network evaluation at one pixel; `MFLOPs/image pixel` is a whole render (per-view "
            "precomputation included) divided by the pixels of the image. Reference notes: "
            f"{REFERENCE_NOTES['mflops_per_pixel']} MFLOPs/pixel, ~{REFERENCE_NOTES['ms_128']:.0f} "
            "ms per 128x128 render.\n\n" + "\n".join(f"- {k}: {v:.1f}x" for k, v in ratios.items()),
            "## Training step\n\n"
            + (markdown_table(train_rows) if train_rows else "(skipped)")
            + "\n\nOne step = sample the batch, forward 2000 points per view (1500 silhouette, "
            "500 in-mask), backward, clip, AdamW. Peak RSS of a fresh process holding the cached "
            "data set; `RSS over data` is the growth after loading the data.",
        ]
    )
    if acc_extra.get("curves"):
        curve_lines = []
        for name, rows in acc_extra["curves"].items():
            for r in rows:
                curve_lines.append(
                    {
                        "model": name,
                        "step": r.get("step"),
                        "minutes": float(r.get("minutes", "nan")),
                        **{
                            k.replace("eval/", ""): float(v)
                            for k, v in r.items()
                            if k.startswith("eval/")
                            and ("iou" in k or "nnopcs_mse" in k or "depth_mae" in k)
                            and "min" not in k
                            and not k.startswith("eval/train")
                        },
                    }
                )
        notes += "\n\n## Learning curves (evaluation subsets during training)\n\n" + markdown_table(
            curve_lines
        )
        equal = _equal_steps(curve_lines)
        if equal:
            notes += (
                "\n\n## Reference next to ours\n\nEach evaluation of the reference-size run "
                "next to the evaluation of our run with the nearest step count, not the "
                "same step count unless the runs allow it (the "
                "training runs' own evaluation subsets, `netepu.eval.eval_views` views "
                "per set).\n\n" + markdown_table(equal)
            )
    if args.light:
        notes = (
            "**Light run** (`--light`): no render timings; accuracy on the `--slow-views` "
            "subsets only; the reference's dense render is counted as its per-view part plus "
            "(pixels x FLOPs per query) instead of being run.\n\n" + notes
        )
    write_report(
        "netepu_geometry",
        "NeTePu geometry: accuracy and cost",
        acc_rows,
        notes,
        extra={
            "cost": cost_rows,
            "training": train_rows,
            "ratios": ratios,
            **acc_extra,
            "paper": PAPER,
            "reference_notes": REFERENCE_NOTES,
        },
    )


if __name__ == "__main__":
    main()
