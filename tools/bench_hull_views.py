"""The visual hull: views per voxel and pixel ownership, before against now.

    .venv/bin/python tools/bench_hull_views.py          # ~20 minutes on 2 cores

A voxel of the hull is kept when every camera that sees it shows foreground there and at
least ``min_views`` cameras see it (:func:`nsd.cues.occupancy.hull_min_views`); a foreground
pixel goes to the front-most individual with a voxel projecting within ``OWNER_RADIUS`` voxel
sides of it (:func:`nsd.cues.occupancy.owned_pixels`). This scores the hull-only
decomposition (:mod:`nsd.evaluation.hull_baseline`: no learning; the same hull places NSD's
windows, gives their depths and links the views at inference and makes the training priors)
before (``min_views`` 2, radius 1.5), with the majority alone, and now (majority, radius
0.6), then every ``min_views`` from 2 to the number of cameras at the new radius, on
synthetic scenes of 2-6 individuals, 4-8 cameras, apart and in contact (``nsd-synth``, seeds
fixed), on 30 held-out frames each, at 128 x 128. Metrics as ``nsd-eval``
(nsd/evaluation/decomposition.py).

Writes ``docs/benchmarks/hull_views.{md,json}``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.cues import occupancy  # noqa: E402
from nsd.cues.occupancy import hull_min_views, voxel_grid  # noqa: E402
from nsd.evaluation.hull_baseline import evaluate_hull  # noqa: E402
from nsd.io.ground_truth import GroundTruth  # noqa: E402
from nsd.io.scene_data import SceneData  # noqa: E402
from nsd.synth.scene import default_scene  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

BIN = Path(sys.executable).parent
SCENES = {  # name -> (individuals, nsd-synth overrides)
    "default scene (2 bipeds, 4 cameras)": (2, None),
    "2 bipeds huddling, 4 cameras": (
        2, ["num_individuals=2", "motion.interaction=huddle", "seed=1"]),
    "3 bipeds huddling, 4 cameras": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=1"]),
    "3 bipeds huddling, 4 cameras, seed 2": (
        3, ["num_individuals=3", "motion.interaction=huddle", "seed=2"]),
    "3 bipeds free, 6-camera ring": (
        3, ["num_individuals=3", "rig.kind=ring", "rig.count=6", "motion.area_radius=2.5",
            "motion.interaction=free", "seed=4"]),
    "4 (bipeds, quadrupeds) huddling, 8 cameras": (
        4, ["num_individuals=4", "species=[biped,quadruped]", "rig.count=8",
            "motion.area_radius=2.0", "motion.interaction=huddle", "seed=1"]),
    "6 bipeds huddling, 8 cameras": (
        6, ["num_individuals=6", "rig.count=8", "motion.area_radius=2.0",
            "motion.interaction=huddle", "seed=1"]),
}
METRICS = ("detection_rate", "mask_miou", "depth_order_accuracy", "association_accuracy",
           "merge_rate", "detection_rate_touching", "mask_miou_touching", "touching_share")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="held-out frames scored per scene")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), help="scene names to run")
    args = ap.parse_args()
    torch.set_num_threads(2)
    root = Path(tempfile.mkdtemp(prefix="bench-hull-views-"))
    now = occupancy.OWNER_RADIUS
    rows = []
    for i, name in enumerate(args.scenes):
        k, synth = SCENES[name]
        scene = default_scene() if synth is None else root / f"scene{i}"
        if synth is not None:
            subprocess.run([str(BIN / "nsd-synth"), f"out={scene}", *synth], check=True,
                           capture_output=True)
        data = SceneData(scene, (128, 128))
        gt = GroundTruth.load(scene)
        idx = np.asarray(data.heldout_frames)
        idx = idx[np.linspace(0, len(idx) - 1, args.frames).round().astype(int)]
        V = data.num_views
        auto = hull_min_views(V)
        settings = [("2", 1.5, "before"), ("auto", 1.5, "majority"), ("auto", now, "now")]
        settings += [(str(n), now, "") for n in range(2, V + 1) if n != auto]
        for views, radius, label in settings:
            grid = voxel_grid(data.rig, data.frame_hw, 48, min_views=views)
            occupancy.OWNER_RADIUS = radius  # read by multiview_proposals at each call
            t0 = time.perf_counter()
            m = evaluate_hull(data, idx, gt, grid, k)
            row = {"scene": name, "cameras": V, "rule": label,
                   "min_views": f"auto ({auto})" if views == "auto" else views,
                   "owner_radius": radius}
            row.update({key: m.get(key) for key in METRICS})
            row["s_per_frame"] = (time.perf_counter() - t0) / len(idx)
            rows.append(row)
            print(row, flush=True)
        occupancy.OWNER_RADIUS = now
    write_report(
        "hull_views", "The visual hull: views per voxel and pixel ownership, before and now", rows,
        notes=("Hull-only decomposition (nsd/evaluation/hull_baseline.py, no learning) of "
               f"{args.frames} held-out frames per scene at 128 x 128, 48^3 voxels, with "
               "`min_views` cameras required to see a voxel (every camera that sees it must "
               "show foreground there) and a pixel owned by the front-most individual with a "
               "voxel within `owner_radius` voxel sides (nsd/cues/occupancy.py). `before`: "
               "the rule until this table; `now`: `auto` (a majority of the cameras, the "
               "default of `inference.min_views` and `prior_proposal.min_views`) and radius "
               "0.6. Touching columns: instants where two "
               "individuals' amodal masks overlap in most cameras that see both "
               "(nsd/evaluation/contact.py). Scenes: `nsd-synth` with the overrides in "
               "tools/bench_hull_views.py (seed 1 unless stated; the default scene is "
               "`nsd-run`'s built-in one)."),
    )


if __name__ == "__main__":
    main()
