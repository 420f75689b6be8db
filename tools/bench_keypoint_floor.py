"""Where the keypoint error of inverse rendering comes from, species by species.

    .venv/bin/python tools/bench_keypoint_floor.py [--run RUN ...] [--frame-step 20]
        [--models NAME=DIR ...]

The inversion (:mod:`netepu.geometry.inverse`) searches the geometry model's global code
``z``; the keypoints it returns are the code's decoded keypoints. So its error has floors
that no mask and no optimiser removes. For each shipped model (biped, quadruped), in mm:

* ``round trip``: poses encoded and decoded (``model.encode``), what a start from the
  encoder loses;
* ``decodable``: the closest decoded keypoints to each pose over every code and translation
  (Adam on ``z`` and ``c`` from the encoded code, ``--fit-steps`` steps, the mean keypoint
  distance as loss): the decoder's range, the floor of any inversion;

on poses of the model's own body (the one individual it was trained on, fresh poses) and on
poses of the synthetic world's bodies (``proportion_variation`` 1, its default: every
individual has its own proportions, as in every ``nsd-synth`` scene).

With ``--run`` (``nsd-run`` folders of synthetic scenes): the same two floors on that scene's
ground-truth poses (every ``--frame-step``-th frame), then the inversion with the
``netepu.keypoints`` defaults from the ground truth's amodal masks (no mask error) and from
the exported masks (what the pipeline gives), on every ``--frame-step``-th exported frame, one
thread. ``--geometry``: each model's renders of its data's held-out views too (silhouette IoU,
NNOPCS MSE, depth MAE: what the pose code must not spoil). ``--models NAME=DIR``: models
folders to compare (default the shipped ``netepu/pipeline/models/``), named in the ``models``
column. Writes
``docs/benchmarks/keypoint_floor.{md,json}`` (``--report``: another name; ``--species``: one
body only).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netepu.geometry.data import DataConfig, build_geometry_data  # noqa: E402
from netepu.geometry.evaluation import evaluate_views  # noqa: E402
from netepu.geometry.maps import MapSettings  # noqa: E402
from netepu.geometry.model import load_geometry_model  # noqa: E402
from netepu.geometry.pose_code import fresh_poses, round_trip_error  # noqa: E402
from netepu.pipeline.species_models import MODELS, builtin_initialisers  # noqa: E402
from netepu.pipeline.subject_keypoints import invert_export  # noqa: E402
from nsd.io.ground_truth import GroundTruth  # noqa: E402
from tools.bench_keypoints import errors, run_scene, truth_export  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

SPECIES = ("biped", "quadruped")


def floors(model, poses: torch.Tensor, steps: int) -> dict[str, float]:
    """Round-trip and decodable errors (mm, mean / median / 90th percentile over poses) of
    ``poses`` (n, K, 3) in metres."""
    for p in model.parameters():
        p.requires_grad_(False)
    trip = round_trip_error(model, poses)
    with torch.no_grad():
        code = model.encode(poses)
    z = code.z.clone().requires_grad_(True)
    centre = code.centre.clone().requires_grad_(True)
    opt = torch.optim.Adam([z, centre], lr=0.01)
    for _ in range(steps):
        dist = (model.decode(z, centre).keypoints - poses).norm(dim=-1).mean(1)
        opt.zero_grad()
        dist.sum().backward()
        opt.step()
    with torch.no_grad():
        best = (model.decode(z, centre).keypoints - poses).norm(dim=-1).mean(1)
    out = {}
    for name, e in (("round_trip", trip), ("decodable", torch.minimum(best, trip))):
        e = 1000 * e.double().numpy()
        out |= {f"{name}_mm": float(e.mean()), f"{name}_median_mm": float(np.median(e)),
                f"{name}_p90_mm": float(np.percentile(e, 90))}
    return out


def renders(model, config: dict) -> dict[str, float]:
    """Silhouette IoU, NNOPCS MSE and depth MAE (mm) on every held-out view of the model's
    data (held-out poses; held-out poses seen by held-out cameras)."""
    data = build_geometry_data(config["netepu"]["data"])
    render = MapSettings.from_config(config["netepu"]["render"])
    out = {}
    with torch.no_grad():
        for name, short in (("heldout_poses", "poses"), ("heldout_cameras", "cameras")):
            m = evaluate_views(model, data.evaluation[name], render)
            out |= {f"{short}_iou": m["iou"], f"{short}_nnopcs_mse": m["nnopcs_mse"],
                    f"{short}_depth_mae_mm": m["depth_mae_mm"]}
    return out


def invert(run: Path, scene: str, models: Path, species: str, kind: str, step: int,
           out: Path) -> dict:
    """MPJPE of the default inversion (into ``out``) of ``run``'s export (``kind``
    ``export``) or of the ground truth's amodal masks of its rows (``amodal``, made once in
    ``out``'s parent), and seconds per subject-frame."""
    export = run / "export"
    if kind == "amodal":
        export = out.parent / f"{run.name}_amodal"
        if not (export / "subjects.coco.json").is_file():
            truth_export(run / "export", scene, export, "amodal")
    t = time.perf_counter()
    s = invert_export(export, scene, models / f"{species}.pt", out, frame_step=step,
                      occlusion=kind == "export",
                      initialiser=models / builtin_initialisers(models)[species]["file"])
    seconds = (time.perf_counter() - t) / max(1, s["subject_frames"])
    e = errors(export, scene, out / "keypoints3d.npz")
    return {"mpjpe_mm": e["mpjpe_mm"], "median_mm": e["median_mm"], "p90_mm": e["p90_mm"],
            "scored": e["scored"], "s_per_subject_frame": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, nargs="*", default=[],
                    help="nsd-run folders of synthetic scenes of one species each")
    ap.add_argument("--frame-step", type=int, default=20)
    ap.add_argument("--poses", type=int, default=200, help="poses of each body set")
    ap.add_argument("--fit-steps", type=int, default=600, help="Adam steps of 'decodable'")
    ap.add_argument("--models", nargs="+", default=[f"shipped={MODELS}"],
                    help="NAME=DIR models folders (biped.pt, quadruped.pt, models.json)")
    ap.add_argument("--geometry", action="store_true",
                    help="also each model's renders of its held-out views (IoU, NNOPCS, depth)")
    ap.add_argument("--species", nargs="+", choices=SPECIES, default=list(SPECIES),
                    help="the bodies whose floors and renders are measured (default: both)")
    ap.add_argument("--report", default="keypoint_floor")
    args = ap.parse_args()
    rows = []
    work = Path(tempfile.mkdtemp(prefix="bench-keypoint-floor-"))
    torch.set_num_threads(1)  # the inversions' seconds are of one thread
    for entry in args.models:
        torch.manual_seed(0)
        name, _, folder = entry.rpartition("=")
        models = Path(folder)
        name = name or models.name
        for species in args.species:
            model, config = load_geometry_model(models / f"{species}.pt")
            cfg = DataConfig.from_mapping(config["netepu"]["data"])
            if args.geometry:
                rows.append({"models": name, "species": species,
                             "poses": "renders of the held-out views", **renders(model, config)})
                print(rows[-1], flush=True)
            for label, spread in (("its own body, fresh poses", 0.0),
                                  ("the synthetic world's bodies (proportion_variation 1)", 1.0)):
                poses = fresh_poses(cfg, args.poses, np.random.default_rng(12345), spread)
                rows.append({"models": name, "species": species, "poses": label,
                             "n": len(poses), **floors(model, poses, args.fit_steps)})
                print(rows[-1], flush=True)
        for run in args.run:
            scene, species = run_scene(run)
            model, _ = load_geometry_model(models / f"{species}.pt")
            gt = GroundTruth.load(scene)
            poses = torch.cat([torch.as_tensor(np.asarray(kp[::args.frame_step]),
                                               dtype=torch.float32)
                               for kp in gt.scene.keypoints3d.values()])
            row = {"models": name, "species": species,
                   "poses": f"scene `{Path(scene).name}` (run `{run.name}`), "
                   f"{len(gt.scene.keypoints3d)} individuals", "n": len(poses),
                   **floors(model, poses, args.fit_steps)}
            for kind in ("amodal", "export"):
                e = invert(run, scene, models, species, kind, args.frame_step,
                           work / f"{name}_{run.name}_{kind}")
                row |= {f"{kind}_{k}": v for k, v in e.items()}
            rows.append(row)
            print(rows[-1], flush=True)
    write_report(
        args.report, "Where the keypoint error of inverse rendering comes from", rows,
        notes=("mm, mean over poses (`_median`, `_p90`: over poses). `round_trip`: encode and "
               "decode. `decodable`: the closest decoded keypoints over all codes (Adam on the "
               f"code and translation, {args.fit_steps} steps, from the encoded code; never "
               "above the round trip): the floor of any inversion with this model. Scene rows: "
               f"every {args.frame_step}th frame; `amodal_*`: the default inversion "
               "(`netepu.keypoints` defaults, one thread) from the ground truth's amodal masks "
               "of the exported rows' individuals, no occluders; `export_*`: from the exported "
               "masks with occluders, as `nsd-run` does. `models`: the models folder of the row "
               "(`shipped`: `netepu/pipeline/models/` at this commit)."))


if __name__ == "__main__":
    main()
