"""NeTePu's texture ablations in both PSNR protocols, and where the paper's gaps come from.

Writes ``docs/benchmarks/netepu_texture_ablations.md`` and ``.json`` and
``docs/images/netepu_texture_ablations.jpg``.

NeTePu (table 3 and sec. 5.3) reports colour PSNR 19.35 dB for the full model, 13.63 dB
without NNOPCS maps and 14.74 dB without per-keypoint texture features. Nine texture
models answer whether those gaps appear here and why: the three rows of the paper for
two colour renderers and two encoder inputs,

* ``ours``: the renderer reads the frozen geometry's keypoint features f and code z
  beside the texture's (``renderer_geometry: true``; the paper's text: "we augment the
  local features for geometry f with f_texture");
* ``ref``: the renderer reads f_texture and z_texture only, as NeTePu's code does
  (``NePuTextureRenderer``); without f_texture its keypoints carry their positions only;
* ``frame``: our renderer, but the encoder reads the whole view (``crop_margin: null``,
  128 x 128 for the 256 x 192 view) wherever the body is, as NeTePu's encoder reads the
  whole frame, instead of a square crop around the visible mask (64 x 64).

Every model is trained on the shipped biped geometry (frozen), with the shipped texture
recipe otherwise (conf/netepu/texture/default.yaml) and the same 2,083 steps, one
thread, the trainer's seed. Each is scored in both protocols (:mod:`nsd.evaluation.maps`):
ours (PSNR over the ground-truth foreground) and NeTePu's (the whole 8-bit image,
the render zero outside the ground-truth mask); with the code of the view itself
(reconstruction, NeTePu's test) and with the code of another held-out pose seen by
another camera (texture swap: novel pose and view synthesis)::

    .venv/bin/python tools/bench_texture_ablations.py geometry     # the shipped biped's geometry
    taskset -c 0 .venv/bin/python tools/bench_texture_ablations.py train ours   # ~13 min each
    ... train ours_no_nnopcs / ours_no_local / ref / ref_no_nnopcs / ref_no_local
    ... train frame / frame_no_nnopcs / frame_no_local   # ~60 min each (the encoder at 128 x 128)
    taskset -c 0 .venv/bin/python tools/bench_texture_ablations.py evaluate ours   # each run
    .venv/bin/python tools/bench_texture_ablations.py report
    taskset -c 0 .venv/bin/python tools/bench_texture_ablations.py stability ours  # eval every 100
    .venv/bin/python tools/bench_texture_ablations.py stability-report
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import markdown_table, write_report  # noqa: E402

WORK = ROOT / "runs" / "texture_ablations"
GEOMETRY = WORK / "geometry_biped.pt"
STEPS = 2083  # the shipped texture recipe's (tools/train_species_models.py)
NO_NNOPCS = ["netepu.texture.model.use_nnopcs=false", "netepu.texture.model.use_normals=false"]
NO_LOCAL = ["netepu.texture.model.local_features=false"]
REF = ["netepu.texture.model.renderer_geometry=false"]
FRAME = ["netepu.texture.model.crop_margin=null", "netepu.texture.model.crop_size=128"]
VARIANTS = {  # name: netepu-train overrides
    "ours": [],
    "ours_no_nnopcs": NO_NNOPCS,
    "ours_no_local": NO_LOCAL,
    "ref": REF,
    "ref_no_nnopcs": REF + NO_NNOPCS,
    "ref_no_local": REF + NO_LOCAL,
    "frame": FRAME,
    "frame_no_nnopcs": FRAME + NO_NNOPCS,
    "frame_no_local": FRAME + NO_LOCAL,
}
LABELS = {
    "ours": "ours: renderer reads f, z (+ f_texture, z_texture)",
    "ours_no_nnopcs": "ours, no NNOPCS (RGB-only encoder)",
    "ours_no_local": "ours, no per-keypoint texture features",
    "ref": "NeTePu's code: renderer reads f_texture, z_texture only",
    "ref_no_nnopcs": "NeTePu's code, no NNOPCS",
    "ref_no_local": "NeTePu's code, no per-keypoint texture features",
    "frame": "whole frame: ours, the encoder reads the whole view (128 x 128)",
    "frame_no_nnopcs": "whole frame, no NNOPCS",
    "frame_no_local": "whole frame, no per-keypoint texture features",
}
PAPER = {"full": 19.35, "no_nnopcs": 13.63, "no_local": 14.74}  # NeTePu tables 2 and 3 (dB)
SETS = ("heldout_poses", "heldout_cameras")
KINDS = {"reconstruction": "reconstruction", "novel": "texture swap"}
GRID_TEXTURES = [0, 3, 9]
FIRST_UNSEEN = 100  # generated texture ids from here on (nsd.synth.texture), never in the pool


def make_geometry() -> None:
    """The shipped biped's geometry module as a geometry checkpoint (``init_from``)."""
    from netepu.pipeline.species_models import MODELS
    from nsd.core.atomic import atomic_save_torch
    from nsd.core.trainer import load_checkpoint

    state = load_checkpoint(MODELS / "biped.pt")
    keep = {k: state[k] for k in ("format", "config", "step")}
    atomic_save_torch({**keep, "modules": {"geometry": state["modules"]["geometry"]}}, GEOMETRY)
    print(GEOMETRY)


def train(name: str, stability_minutes: float | None = None) -> None:
    """One model's run in ``WORK/name``; with ``stability_minutes``, the same run with the
    trainer's evaluation every 100 steps, stopped after that many minutes (0: all steps),
    in ``WORK/stability_<name>``: how much a model's PSNR moves between evaluations."""
    from netepu.cli.train import run
    from nsd.core.config import compose_app

    extra = ([] if stability_minutes is None else
             ["trainer.eval_every=100", "trainer.grid_every=100000"])  # fmt: skip
    cfg = compose_app("netepu_train", [
        *VARIANTS[name], "stage=texture", f"init_from={GEOMETRY}", f"trainer.max_steps={STEPS}",
        f"trainer.max_minutes={stability_minutes or 0}", "trainer.progress=false", "threads=1",
        "device=cpu", *extra,
    ])  # fmt: skip
    out = WORK / (name if stability_minutes is None else f"stability_{name}")
    print(json.dumps(run(cfg, out)))


def stability_report() -> None:
    """The trainer's 8-view PSNR (held-out poses, reconstruction) at every evaluation of
    the stability runs and of the main runs."""
    import csv
    from itertools import pairwise

    key = "eval/heldout_poses/psnr_reconstruction"
    rows = []
    for folder in sorted(WORK.glob("*/metrics.csv")):
        with folder.open() as f:
            curve = {int(r["step"]): round(float(r[key]), 2) for r in csv.DictReader(f)
                     if r.get(key)}  # fmt: skip
        if curve:
            steps = sorted(curve)
            moves = [abs(curve[b] - curve[a]) for a, b in pairwise(steps)]
            rows.append({"run": folder.parent.name, "evaluations": len(steps),
                         "largest change between evaluations (dB)": max(moves, default=0.0),
                         "PSNR by step (dB)": " ".join(f"{k}:{v}" for k, v in curve.items())})
    write_report(
        "netepu_texture_stability", "How much a texture model's PSNR moves during training",
        rows,
        notes=("The trainer's own evaluation (the first 8 held-out-pose views with full maps, "
               "reconstruction, our protocol) of each run in runs/texture_ablations: "
               "`stability_<model>` evaluates every 100 steps (`tools/bench_texture_ablations.py "
               "stability <model> --minutes M`, one thread, stopped after M minutes when M > 0), "
               "the other runs at steps 1000, 2000 and the last. The benchmark's own figures "
               "(netepu_texture_ablations.md) are of the last step on all 64 views."),
    )


def evaluate(name: str, unseen: bool) -> None:
    """Both protocols on every held-out view with full maps; re-id; grid cells."""
    import cv2

    from netepu.texture.evaluation import evaluate_colour, synthesis_grid
    from netepu.texture.stage import load_texture_task
    from nsd.evaluation.reid import reid_metrics

    torch.set_num_threads(1)
    t0 = time.time()
    task, state = load_texture_task(WORK / name / "checkpoint.pt",
                                    FIRST_UNSEEN if unseen else None)  # fmt: skip
    name += "_unseen" if unseen else ""
    codes = task.codes()
    row = evaluate_colour(task.texture, task.geometry, task.data, codes)
    h = task.data.heldout
    E, T = codes.shape[:2]
    emb = task.reid_embeddings(task.reid_inputs(codes)).reshape(E * T, -1)
    reid = reid_metrics(emb, np.tile(np.arange(T), E), np.repeat(h["camera"], T))
    row |= {f"reid_{k}": float(v) for k, v in reid.items() if k in ("rank1", "map")}
    row |= {
        "steps": int(state["step"]),
        "train_minutes": float(state["train_seconds"]) / 60,
        "body_share": float(h["mask"].reshape(len(h["mask"]), -1).mean(1).mean()),
        "psnr_views": len(h["psnr_view"]),
        "textures": int(T),
        "evaluate_seconds": time.time() - t0,
    }
    grid = synthesis_grid(task.texture, task.geometry, task.data, codes, False, 2, GRID_TEXTURES)
    cv2.imwrite(str(WORK / f"{name}_grid.png"), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    (WORK / f"{name}.json").write_text(json.dumps(row, indent=1))
    print(name, json.dumps(row))


def _figure(names: list[str], stem: str) -> None:
    """The texture-swap grids of all models stacked, each with its name on the left."""
    import cv2

    parts = []
    for n in names:
        img = cv2.imread(str(WORK / f"{n}_grid.png"))
        if img is None:
            continue
        label = np.full((img.shape[0], 150, 3), 255, np.uint8)
        for i, word in enumerate(n.removesuffix("_unseen").split("_")):
            cv2.putText(label, word, (6, 22 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                        (0, 0, 0), 1, cv2.LINE_AA)  # fmt: skip
        parts.append(np.concatenate([label, img], 1))
        parts.append(np.full((6, label.shape[1] + img.shape[1], 3), 255, np.uint8))
    if parts:
        out = ROOT / "docs" / "images" / f"{stem}.jpg"
        cv2.imwrite(str(out), np.concatenate(parts[:-1], 0), [cv2.IMWRITE_JPEG_QUALITY, 92])


def _earlier_rows() -> tuple[dict[str, dict], dict[str, str]]:
    """The runs of the committed report, and when and where each was measured (a row
    that report had kept from an earlier one keeps its own date)."""
    path = ROOT / "docs" / "benchmarks" / "netepu_texture_ablations.json"
    if not path.is_file():
        return {}, {}
    old = json.loads(path.read_text())
    stamp = f"{old['date']}, `{old['commit']}`"
    kept = old["extra"].get("measured", {})
    runs = old["extra"]["runs"]
    return runs, {n: stamp if kept.get(n, "this run") == "this run" else kept[n] for n in runs}


def report() -> None:
    """The report from the runs' files; a model without one keeps the committed report's
    row (its ``measured`` column says when), so models can be added a few at a time."""
    names = [f"{n}{u}" for u in ("", "_unseen") for n in VARIANTS]
    earlier, when = _earlier_rows()
    rows, measured = {}, {}
    for n in names:
        if (WORK / f"{n}.json").is_file():
            rows[n], measured[n] = json.loads((WORK / f"{n}.json").read_text()), "this run"
        elif n in earlier:
            rows[n], measured[n] = earlier[n], when[n]
    table = []
    for n, r in rows.items():
        unseen = n.endswith("_unseen")
        line = {"model": LABELS[n.removesuffix("_unseen")],
                "textures": "16 unseen (generated)" if unseen else "the 16 trained on"}
        for s in SETS:
            for kind, title in KINDS.items():
                line[f"{s.replace('_', ' ')}, {title}: ours / NeTePu's (dB)"] = (
                    f"{r[f'{s}/psnr_{kind}']:.2f} / {r[f'{s}/psnr_image_{kind}']:.2f}"
                )
        line |= {"re-id rank-1": round(r["reid_rank1"], 4), "re-id mAP": round(r["reid_map"], 4),
                 "steps": r["steps"], "train min": round(r["train_minutes"], 1),
                 "measured": measured[n]}  # fmt: skip
        table.append(line)
    gaps = []
    for unseen in ("", "_unseen"):
        for family in ("ours", "ref", "frame"):
            for ablation in ("no_nnopcs", "no_local"):
                g = {"renderer": LABELS[family].split(":")[0], "ablation": ablation,
                     "textures": "unseen" if unseen else "trained on"}  # fmt: skip
                for kind, title in KINDS.items():
                    for proto, key in (("ours", f"psnr_{kind}"),
                                       ("NeTePu's", f"psnr_image_{kind}")):  # fmt: skip
                        full, abl = rows.get(family + unseen), rows.get(
                            f"{family}_{ablation}{unseen}")
                        g[f"{title}, {proto} protocol (dB)"] = (
                            "" if full is None or abl is None else
                            round(full[f"heldout_poses/{key}"] - abl[f"heldout_poses/{key}"], 2))
                g["paper (dB)"] = round(PAPER["full"] - PAPER[ablation], 2)
                gaps.append(g)
    share = np.mean([r["body_share"] for r in rows.values()]) if rows else float("nan")
    notes = [
        "Gaps: the full model's PSNR minus the ablation's, held-out poses seen by the training "
        "cameras (the paper's test set is novel poses of its 24 training cameras); on the 16 "
        "pool textures every model was trained on, and on 16 generated textures none saw "
        f"(ids {FIRST_UNSEEN}-{FIRST_UNSEEN + 15}, same poses and cameras).\n",
        markdown_table(gaps),
        "",
        f"NeTePu's protocol: the render is stored as 8 bits with zeros outside the ground-truth "
        f"mask and compared with the whole 8-bit ground-truth image. The synthetic views "
        f"have a black background, and the body covers {100 * share:.1f} % of a held-out view "
        f"on average, so NeTePu's figure is ours raised by about "
        f"10 log10(1 / share) per view: the two protocols rank the models alike.\n",
        f"Every model: {STEPS} steps of 16 samples, one thread, the shipped biped geometry "
        f"frozen, conf/netepu/texture/default.yaml otherwise; scored on "
        f"{next(iter(rows.values()))['psnr_views'] if rows else 0} held-out views x 16 "
        "textures per protocol and code (8 held-out poses, 4 training + 4 held-out cameras "
        "each). Texture swap: the code of another held-out pose seen by another camera. "
        "Grids (docs/images/netepu_texture_ablations.jpg, ..._unseen.jpg for the generated "
        f"textures): per model and the 1st, 4th and 10th texture ({GRID_TEXTURES}), the source "
        "crop, then ground truth and render of two other held-out poses.\n",
        "`train min`: wall minutes of training while two runs and evaluations shared the two "
        "cores (a step count is the budget here, not a speed figure).",
    ]
    # the grids of this run's models; beside the committed figures when others are kept
    fresh = [n for n in rows if measured[n] == "this run"]
    families = sorted({n.split("_")[0] for n in fresh})
    tag = "" if len(fresh) == len(rows) else "_" + "_".join(families)
    _figure([n for n in fresh if not n.endswith("_unseen")], f"netepu_texture_ablations{tag}")
    _figure([n for n in fresh if n.endswith("_unseen")], f"netepu_texture_ablations{tag}_unseen")
    write_report(
        "netepu_texture_ablations",
        "NeTePu's texture ablations in both PSNR protocols",
        table,
        notes="\n".join(notes),
        extra={"runs": rows, "measured": measured, "gaps": gaps, "paper": PAPER,
               "variants": VARIANTS},
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["geometry", "train", "evaluate", "report", "stability",
                                    "stability-report"])
    p.add_argument("--minutes", type=float, default=0.0,
                   help="stability: stop the run after this many minutes (0: all steps)")
    p.add_argument("name", nargs="?", choices=sorted(VARIANTS))
    p.add_argument("--unseen", action="store_true",
                   help="evaluate: on generated textures the model never saw")  # fmt: skip
    a = p.parse_args()
    WORK.mkdir(parents=True, exist_ok=True)
    if a.what in ("train", "evaluate", "stability") and a.name is None:
        p.error(f"{a.what} needs a model name")
    if a.what == "geometry":
        make_geometry()
    elif a.what == "train":
        train(a.name)
    elif a.what == "stability":
        train(a.name, a.minutes)
    elif a.what == "stability-report":
        stability_report()
    elif a.what == "evaluate":
        evaluate(a.name, a.unseen)
    else:
        report()


if __name__ == "__main__":
    main()
