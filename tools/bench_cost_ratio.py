"""What our geometry renderer saves against the NePu-size reference at equal accuracy.

Writes ``docs/benchmarks/netepu_cost_ratio.md`` and ``.json``.

Two biped geometry runs, each on one core with one thread, side by side (pin them:
``taskset -c 0`` and ``taskset -c 1``), both evaluated during training on the same
held-out views (``netepu.eval.eval_views`` per set, coarse-to-fine renders):

* ``ours``: the shipped biped recipe (tools/train_species_models.py) for its first
  1,000 steps, evaluated every 100 steps;
* ``reference``: the NePu-size networks (``conf/netepu/model/reference.yaml``, the
  authors' sizes, 38 M parameters) with our losses, batch 4 (batch 64 does not fit in
  24 GB) and NePu's learning rate 5e-4, for a budget of training minutes, evaluated at
  fixed training minutes.

For every evaluation of the reference, the training minutes our curve needs to reach
the same held-out-pose IoU (linear interpolation between its evaluations) give the cost
ratio at equal IoU; training minutes exclude evaluations (the trainer's clock)::

    taskset -c 1 .venv/bin/python tools/bench_cost_ratio.py train reference --minutes 60
    taskset -c 0 .venv/bin/python tools/bench_cost_ratio.py train ours
    .venv/bin/python tools/bench_cost_ratio.py report
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import evaluations, write_report  # noqa: E402
from tools.train_species_models import RECIPES  # noqa: E402

WORK = ROOT / "runs" / "cost_ratio"
EVAL_VIEWS = 8
COMMON = ["threads=1", "device=cpu", "trainer.progress=false", "trainer.grid_every=0",
          f"netepu.eval.eval_views={EVAL_VIEWS}"]  # fmt: skip
OURS_STEPS = 1000
REFERENCE = ["netepu/model=reference", "netepu/data=biped", "netepu.optim.batch_size=4",
             "netepu.optim.lr=5e-4", "netepu.optim.lr_decay_every=0"]  # fmt: skip
REFERENCE_EVAL_MINUTES = [2, 5, 10, 20, 30, 45]
METRICS = ("heldout_poses/iou", "heldout_poses/nnopcs_mse", "heldout_poses/depth_mae_mm",
           "heldout_cameras/iou")  # fmt: skip


def train(name: str, minutes: float) -> None:
    from netepu.cli.train import run
    from nsd.core.config import compose_app

    if name == "ours":
        overrides = [*RECIPES["biped"]["geometry"], f"trainer.max_steps={OURS_STEPS}",
                     "trainer.max_minutes=0", "trainer.eval_every=100"]  # fmt: skip
    else:
        marks = [m for m in REFERENCE_EVAL_MINUTES if m < minutes]
        overrides = [*REFERENCE, "trainer.max_steps=0", f"trainer.max_minutes={minutes}",
                     "trainer.eval_every=0", f"trainer.eval_at_minutes={marks}".replace(" ", "")]
    cfg = compose_app("netepu_train", [*overrides, *COMMON])
    print(json.dumps(run(cfg, WORK / name)))


def curve(name: str) -> list[dict]:
    """The run's evaluations: step, training minutes and :data:`METRICS`."""
    return [{"step": int(r["step"]), "minutes": float(r["minutes"]),
             **{m: float(r[f"eval/{m}"]) for m in METRICS}}
            for r in evaluations(WORK / name, f"eval/{METRICS[0]}")]


def minutes_to_reach(ours: list[dict], iou: float) -> tuple[float | None, bool]:
    """Training minutes our curve needs to reach ``iou`` and whether that is a measurement
    (linear between two evaluations, the curve made monotone by its running maximum) or
    only an upper bound (``iou`` at or below our first evaluation: its minutes); None
    when our curve never reaches it."""
    t = np.array([r["minutes"] for r in ours])
    y = np.maximum.accumulate(np.array([r["heldout_poses/iou"] for r in ours]))
    if not len(y) or iou > y[-1]:
        return None, False
    i = int(np.argmax(y >= iou))
    if i == 0:
        return float(t[0]), False
    return float(t[i - 1] + (iou - y[i - 1]) / (y[i] - y[i - 1]) * (t[i] - t[i - 1])), True


def report() -> None:
    ours, ref = curve("ours"), curve("reference")
    rows = []
    for r in ref:
        t, exact = minutes_to_reach(ours, r["heldout_poses/iou"])
        bound = "" if exact else "<= "
        rows.append({
            "reference step": r["step"], "reference minutes": round(r["minutes"], 2),
            "held-out poses IoU": round(r["heldout_poses/iou"], 4),
            "NNOPCS MSE": f"{r['heldout_poses/nnopcs_mse']:.2e}",
            "depth MAE mm": round(r["heldout_poses/depth_mae_mm"], 1),
            "ours: minutes to the same IoU": "" if t is None else f"{bound}{t:.2f}",
            "cost ratio (reference / ours)": "" if not t else (
                f"{'>= ' if bound else ''}{r['minutes'] / t:.1f}"),
        })  # fmt: skip
    last = ours[-1] if ours else {}
    notes = [
        "Our curve (same views, same thread): "
        + "; ".join(f"step {o['step']}: {o['minutes']:.2f} min, IoU {o['heldout_poses/iou']:.3f}"
                    for o in ours) + ".",
        "",
        f"Each run on its own core with one thread, evaluated on {EVAL_VIEWS} held-out-pose "
        "views (training cameras), coarse-to-fine renders; minutes are training minutes "
        "(evaluations excluded). The reference is NePu's network sizes "
        "(conf/netepu/model/reference.yaml) trained with our losses at batch 4 and NePu's "
        "learning rate 5e-4 (one run, not tuned). A ratio compares the minutes each model "
        "needs to reach the same held-out IoU (`<=` / `>=`: the reference's IoU lies below our "
        "first evaluation, so our minutes are an upper bound and the ratio a lower bound); "
        "where the reference never reaches our final IoU, the ratio at our final accuracy is "
        "not measured.",
    ]
    write_report(
        "netepu_cost_ratio",
        "NeTePu geometry: training cost of the NePu-size reference against ours at equal IoU",
        rows,
        notes="\n".join(notes),
        extra={"ours": ours, "reference": ref, "ours_final": last,
               "reference_overrides": REFERENCE, "common": COMMON},
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["train", "report"])
    p.add_argument("name", nargs="?", choices=["ours", "reference"])
    p.add_argument("--minutes", type=float, default=60.0, help="train reference: budget")
    a = p.parse_args()
    WORK.mkdir(parents=True, exist_ok=True)
    if a.what == "train":
        if a.name is None:
            p.error("train needs ours or reference")
        train(a.name, a.minutes)
    else:
        report()


if __name__ == "__main__":
    main()
