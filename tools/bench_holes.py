"""Speckled masks: the visible masks with their small holes filled, learned and hull-only.

    .venv/bin/python tools/bench_holes.py RUN [RUN ...] --label NAME ...   # nsd-run folders

Every visible mask is drawn from the background residual, so where a body's colour is close
to the floor's its mask comes out speckled. ``inference.hole_share`` fills the holes a mask
encloses, up to that share of its area, where no other subject shows (:mod:`nsd.cues.holes`).
For each run (an ``nsd-run`` folder with ``train/checkpoint.pt`` and the scene of its
``scene/stage.json``) and each ``--shares`` value, ``nsd-eval`` scores the trained
checkpoint on ``--frames`` frames of the held-out tail: the learned decomposition and the
hull-only row (:mod:`nsd.evaluation.hull_baseline`, which fills its masks the same way),
split apart / touching. Nothing is trained; the runs' checkpoints are evaluated as they are.

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
KEYS = ("detection_rate", "mask_miou", "mask_miou_touching", "detection_rate_touching",
        "merge_rate", "association_accuracy")


def _evaluate(run: Path, share: float, frames: int, out: Path) -> dict:
    """``nsd-eval``'s metrics of ``run``'s checkpoint with ``inference.hole_share=share``."""
    scene = json.loads((run / "scene" / "stage.json").read_text())["summary"]["path"]
    subprocess.run([str(BIN / "nsd-eval"), f"checkpoint={run / 'train' / 'checkpoint.pt'}",
                    f"scene={scene}", f"max_frames={frames}", f"inference.hole_share={share}",
                    f"out={out}"], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return json.loads((out / "eval.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="nsd-run folders")
    ap.add_argument("--label", nargs="+", default=None, help="a name per run (default: its folder)")
    ap.add_argument("--shares", nargs="+", type=float, default=[0.0, 0.02, 0.04, 0.08])
    ap.add_argument("--frames", type=int, default=30, help="held-out frames scored per run")
    ap.add_argument("--report", default="holes", help="docs/benchmarks/<report>.{md,json}")
    args = ap.parse_args()
    labels = args.label or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        raise SystemExit("--label: one name per run")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-holes-") as tmp:
        for run, label in zip(args.runs, labels, strict=True):
            for share in args.shares:
                m = _evaluate(run, share, args.frames, Path(tmp) / f"{run.name}-{share}")
                for method, prefix in (("learned", ""), ("hull-only", "hull_")):
                    row = {"run": label, "method": method, "hole_share": share,
                           "touching_share": m.get("touching_share")}
                    row |= {key: m.get(prefix + key) for key in KEYS}
                    rows.append(row)
                    print(row, flush=True)
    write_report(
        args.report, "Speckled masks: small holes filled, learned and hull-only", rows,
        notes=("`nsd-eval` of each run's trained checkpoint on "
               f"{args.frames} frames of its scene's held-out tail with "
               "`inference.hole_share` = `hole_share` (0: off; nsd/cues/holes.py): the holes "
               "a visible mask encloses, up to that share of its area, are filled where no "
               "other subject shows. `learned`: the trained decomposition (multi-view "
               "inference); `hull-only`: the visual hull of the residuals alone, its masks "
               "filled the same way. Metrics as nsd-eval's (nsd/evaluation/decomposition.py): "
               "detection by box IoU >= 0.5 after matching on mask IoU, visible-mask mIoU, "
               "split apart / touching by nsd/evaluation/contact.py."))


if __name__ == "__main__":
    main()
