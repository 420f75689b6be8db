"""The foreground cut of the background residual: foreground IoU and the hull-only decomposition.

    .venv/bin/python tools/bench_evidence.py      # ~5 minutes on 2 cores

Every cue of the toolkit starts from the foreground evidence of the background residual
(:mod:`nsd.cues.evidence`); a pixel is foreground where its mean channel residual exceeds
``threshold + softness / 2``. This script scores that cut on synthetic scenes, one of them
written as lossy video (codec noise), on every 15th frame of every camera:

* ``foreground IoU``: the foreground mask against the union of the ground-truth visible masks;
* the hull-only decomposition (:mod:`nsd.evaluation.hull_baseline`) on every 10th frame:
  detection, visible-mask mIoU, cross-view association and depth order.

Writes ``docs/benchmarks/evidence.{md,json}``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence
from nsd.evaluation.hull_baseline import evaluate_hull
from nsd.inference.multiview import InferenceSettings
from nsd.io.ground_truth import GroundTruth
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from tools.benchlib import write_report

BIN = Path(sys.executable).parent
SCENES = {  # name -> (individuals, nsd-synth overrides; None: the built-in default scene)
    "default (2 bipeds, close)": (2, None),
    "3 bipeds, huddle": (3, ["num_individuals=3", "motion.interaction=huddle", "seed=1"]),
    "3 bipeds, huddle, lossy video": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=1", "video=true"]),
    "3 bipeds, close": (3, ["num_individuals=3", "seed=2"]),
}
CUTS = ((0.04, 0.08), (0.03, 0.06), (0.02, 0.04), (0.01, 0.02))  # (threshold, softness)
HULL = ("detection_rate", "mask_miou", "association_accuracy", "depth_order_accuracy")


def _foreground_iou(data: SceneData, gt: GroundTruth, threshold: float, softness: float):
    ious = []
    for t in range(0, len(data.frames), 15):
        views, bgs = data.views(t)
        fg = (foreground_evidence(views, bgs, threshold, softness) > 0.5).numpy()
        for v, cam in enumerate(data.rig.names):
            g = gt.frame(cam, t, data.frame_hw).visible.any(0)
            ious.append((fg[v] & g).sum() / max((fg[v] | g).sum(), 1))
    return float(np.mean(ious))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench-evidence-"))
    rows = []
    for i, (name, (k, synth)) in enumerate(SCENES.items()):
        if synth is None:
            scene = resolve_scene(None)
        else:
            scene = root / f"scene{i}"
            subprocess.run([str(BIN / "nsd-synth"), f"out={scene}", *synth], check=True,
                           capture_output=True)
        data, gt = SceneData(scene, (128, 128)), GroundTruth.load(scene)
        grid = InferenceSettings.defaults().grid(data.rig, data.frame_hw)
        frames = np.arange(0, len(data.frames), 10)
        for threshold, softness in CUTS:
            hull = evaluate_hull(data, frames, gt, grid, k, True, evidence_threshold=threshold,
                                 evidence_softness=softness)
            rows.append({
                "scene": name, "threshold": threshold, "softness": softness,
                "cut": threshold + softness / 2,
                "default": (threshold, softness) == (EVIDENCE_THRESHOLD, EVIDENCE_SOFTNESS),
                "foreground_iou": _foreground_iou(data, gt, threshold, softness),
                **{f"hull_{key}": hull[key] for key in HULL},
                **{f"hull_{key}_touching": hull[f"{key}_touching"] for key in HULL[:3]},
            })
            print(rows[-1], flush=True)
    write_report(
        "evidence", "Foreground evidence: the residual cut, foreground IoU and the hull-only "
        "decomposition", rows,
        notes=("Mean channel residual |I - B| against the per-camera median background at "
               "128 x 128; `cut` = threshold + softness / 2 (evidence 0.5). Foreground IoU on "
               "every 15th frame of every camera; hull-only metrics (k = the number of "
               "individuals, nsd/evaluation/hull_baseline.py) on every 10th frame. "
               "`default`: the toolkit's setting (nsd/cues/evidence.py)."),
    )


if __name__ == "__main__":
    main()
