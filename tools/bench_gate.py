"""The hull's gate per scene: each scene's median mixture gain, at three samples of instants.

    .venv/bin/python tools/bench_gate.py --root /tmp/hull-scenes    # ~6 min on 2 cores

Before a sequence is clustered, the hull fits its 3D mixture at
``inference.mixture_scene_sample`` instants spread over the frames it will decompose, and
tries the mixture in that sequence only where the median of their gains (nats per voxel
over the k-means partition, :func:`nsd.cues.clustering.scene_wants_mixture`) reaches
``inference.mixture_scene_gain``. Which instants are read depends on the caller: training
spreads them over the whole recording, ``nsd-eval`` over its scored frames (the held-out
tail), the export over its exported frames. This script gives, per scene of
``tools/bench_hull.py`` (the same files; ``--root`` shares its folder), the median at
three such samples, so that the margin of the shipped bound on each side can be read:
the whole recording, the held-out tail, and every fifth frame of the recording.

Writes ``docs/benchmarks/<--report>.{md,json}`` (default ``hull_gate_gains``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.core.config import compose_app  # noqa: E402
from nsd.cues.clustering import MixtureRules, scene_wants_mixture  # noqa: E402
from nsd.cues.evidence import foreground_evidence  # noqa: E402
from nsd.cues.occupancy import scene_gains, voxel_grid  # noqa: E402
from nsd.io.scene_data import SceneData  # noqa: E402
from tools.bench_hull import SCENES, scene_folder  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

SAMPLES = ("whole recording", "held-out tail", "every fifth frame")


def _evidence(data: SceneData):
    """``evidence(t)``: the foreground evidence (V, H, W) of instant ``t`` of ``data``."""
    return lambda t: foreground_evidence(*data.views(t))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES),
                    help="scene names of tools/bench_hull.py")
    ap.add_argument("--root", type=Path, default=None,
                    help="the folder of the scenes (tools/bench_hull.py's --root; default: a "
                         "new temporary folder); scenes already in it are not generated again")
    ap.add_argument("--report", default="hull_gate_gains",
                    help="docs/benchmarks/<report>.{md,json}")
    args = ap.parse_args()
    torch.set_num_threads(2)
    root = args.root or Path(tempfile.mkdtemp(prefix="bench-gate-"))
    background = str(compose_app("train").data.background)
    rules = MixtureRules.defaults()
    rows = []
    for name in args.scenes:
        k = SCENES[name][0]
        data = SceneData(scene_folder(root, name), (128, 128), background=background)
        grid = voxel_grid(data.rig, (128, 128), 48)
        n = len(data.frames)
        evidence = _evidence(data)
        row = {"scene": name, "cameras": data.num_views, "individuals": k}
        for label, frames in zip(SAMPLES, (np.arange(n), np.asarray(data.heldout_frames),
                                           np.arange(0, n, 5)), strict=True):
            gains = scene_gains(evidence, frames, grid, k, rules=rules)
            row[f"median gain, {label}"] = float(np.median(gains)) if gains else None
            row[f"mixture, {label}"] = scene_wants_mixture(gains, rules.mixture_scene_gain)
        rows.append(row)
        print(row, flush=True)
    write_report(
        args.report, "The hull's gate per scene: median mixture gains at three samples", rows,
        notes=(f"Per scene of tools/bench_hull.py (128 x 128, 48^3 voxels, background "
               f"`{background}`), the median of the 3D mixture's gains over the k-means "
               f"(nats per voxel) at {rules.mixture_scene_sample} instants spread evenly over "
               "the whole recording (what training reads), the held-out tail (nsd-eval) and "
               "every fifth frame of the recording, each track carried through its instants "
               "(nsd/cues/occupancy.py: scene_track); `mixture`: the gate's decision at the "
               f"shipped `inference.mixture_scene_gain` = {rules.mixture_scene_gain} "
               "(an empty median, every instant's bodies apart: each instant decides)."),
    )


if __name__ == "__main__":
    main()
