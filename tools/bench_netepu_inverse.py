"""Benchmark of inverse rendering: silhouettes from 2, 4 and 8 views -> 3D keypoints.

For held-out poses of the synthetic individual (a pose seed never used in
training) rendered by the training rig, the ground-truth silhouettes of V
input cameras go into :func:`netepu.geometry.inverse.invert_silhouettes` with a
trained geometry model. Reported per V: MPJPE of the recovered keypoints,
silhouette IoU of the recovered body re-rendered in the input views and in all
other cameras of the rig (views the optimisation never saw), and seconds per
inversion. Writes ``docs/benchmarks/netepu_inverse.md`` and ``.json``.

Usage::

    .venv/bin/python tools/bench_netepu_inverse.py runs/netepu/geometry_biped --poses 6
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netepu.geometry.data import build_geometry_data, render_new_poses  # noqa: E402
from netepu.geometry.inverse import InverseSettings, invert_silhouettes  # noqa: E402
from netepu.geometry.maps import MapSettings, render_maps  # noqa: E402
from netepu.geometry.model import load_geometry_model  # noqa: E402
from nsd.evaluation.maps import silhouette_iou  # noqa: E402
from nsd.evaluation.pose import mpjpe  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

POSE_SEED = 12345  # held-out poses: a seed the data set never uses

# input cameras of the NePuMoo rig (3 rings of 8: ring r camera i has index 8 r + i)
VIEW_SETS = {
    2: [8, 10],  # middle ring, 90 degrees apart
    4: [8, 10, 12, 14],  # middle ring, every 90 degrees
    8: [0, 3, 6, 9, 12, 15, 18, 21],  # all three rings, spread in azimuth
}


@torch.no_grad()
def _render_silhouettes(model, z, centre, camera, size) -> torch.Tensor:
    code = model.decode(z[None], centre[None])
    ctx = model.prepare(code, camera)
    return render_maps(model.query, ctx, size, MapSettings.defaults()).silhouette


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run folder of a trained geometry model")
    ap.add_argument("--poses", type=int, default=8, help="held-out poses")
    ap.add_argument("--steps", type=int, default=InverseSettings.steps)
    ap.add_argument("--templates", type=int, default=2, help="training poses used as starts")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (timings depend on it)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    run = ROOT / args.run
    model, config = load_geometry_model(run / "checkpoint.pt")
    data_cfg = config["netepu"]["data"]
    data = build_geometry_data(data_cfg)
    maps, rig = render_new_poses(data.config, args.poses, POSE_SEED)
    cams = rig.stacked(torch.float32)
    size = data.config.image_size
    templates = data.keypoints[: args.templates]
    settings = InverseSettings(steps=args.steps, margin=config["netepu"]["render"]["margin"])
    per_view: dict[int, list[dict]] = {v: [] for v in VIEW_SETS}
    for p in range(args.poses):
        truth = torch.from_numpy(maps["keypoints"][p])
        masks = torch.from_numpy(maps["mask"][p])
        for V, sel in VIEW_SETS.items():
            cam = cams[sel]
            t0 = time.perf_counter()
            res = invert_silhouettes(
                model, masks[sel], cam, templates, settings, np.random.default_rng(p)
            )
            seconds = time.perf_counter() - t0
            others = [c for c in range(len(rig)) if c not in sel]
            sil_in = _render_silhouettes(model, res.z, res.centre, cam, size)
            sil_out = _render_silhouettes(
                model, res.z, res.centre, cams[others], size
            )
            row = {
                "pose": p,
                "views": V,
                "mpjpe_mm": 1000 * float(mpjpe(res.keypoints, truth)),
                "iou_input": float(silhouette_iou(sil_in, masks[sel]).mean()),
                "iou_other": float(silhouette_iou(sil_out, masks[others]).mean()),
                "seconds": seconds,
            }
            per_view[V].append(row)
            print(row, flush=True)
    rows = []
    for V, rs in per_view.items():
        mp = np.array([r["mpjpe_mm"] for r in rs])
        rows.append(
            {
                "input views": V,
                "poses": len(rs),
                "MPJPE mm (mean)": float(mp.mean()),
                "MPJPE mm (median)": float(np.median(mp)),
                "IoU input views": float(np.mean([r["iou_input"] for r in rs])),
                f"IoU other {len(rig) - V} views": float(np.mean([r["iou_other"] for r in rs])),
                "s per inversion": float(np.mean([r["seconds"] for r in rs])),
            }
        )
    notes = (
        f"Model: `{args.run}`. Held-out poses (seed {POSE_SEED}) of the training individual, "
        f"{len(rig)} cameras of the training rig at {size[0]}x{size[1]}; input cameras per V: "
        f"{VIEW_SETS}. Starts: {args.templates} training poses x {settings.headings} headings, "
        f"{settings.steps} Adam steps, {settings.points_per_view} points per view and step, "
        f"{args.threads} torch thread(s) (`s per inversion`), "
        "the worse half of the starts dropped every "
        f"{settings.prune_every} steps. IoU from coarse-to-fine renders of the recovered code."
    )
    write_report(
        "netepu_inverse",
        "NeTePu inverse rendering: silhouettes to 3D keypoints",
        rows,
        notes,
        extra={"per_pose": per_view, "settings": vars(settings)},
    )


if __name__ == "__main__":
    main()
