"""Label-free keypoints from the pipeline's masks: occluders, warm starts, smoothing, speed.

    .venv/bin/python tools/bench_keypoints.py --run RUN [RUN ...] [--work DIR] [--frame-step 10]

Each ``RUN`` is an ``nsd-run`` folder of a synthetic scene (its ``export/`` and the scene named in
its ``pipeline.json``); the shipped geometry model of the scene's species inverts every
``frame-step``-th exported frame (:func:`netepu.pipeline.subject_keypoints.invert_export`),
one variant per fresh process with one torch thread, two at a time on two cores
(``taskset``). The rows:

* the pipeline's masks with each setting (occluders off/on, the screened library of starting
  poses against two templates at four headings, warm starts, fewer loss points, the point
  budget shared by the starts against every start at full points, earlier pruning, the
  learned initialiser's one start against the screened templates, a cheaper screening beside
  it);
* the same subjects with the ground truth's visible masks and amodal masks instead of the
  exported ones (the floor that the masks, 4 cameras and the model leave);
* temporal smoothing of the occlusion-aware fits (``smooth_frames``), applied afterwards;
* ``heading_refits``: the fits refitted turned to their track's heading, ``heading_turned``
  how many of those refits were kept (:mod:`netepu.pipeline.heading`);
* every row whose fits the direction of travel relabelled front to back
  (``travel_relabelled``, :mod:`netepu.pipeline.travel`) again as fitted (``[travel off]``).

MPJPE (mm) against the scene's 3D keypoints (:func:`nsd.evaluation.pose.keypoint_error`),
its percentiles over subject-frames, and seconds per subject-frame; ``mirrored_share``: the
subject-frames closer to the truth with their left and right keypoints swapped (the body
fitted turned front to back, :func:`nsd.evaluation.pose.mirror_errors`), and
``best_of_mirror_mm`` the mean had each taken the closer of the two (what telling front from
back would be worth). Writes
``docs/benchmarks/keypoints.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netepu.pipeline.species_models import MODELS, builtin_initialisers  # noqa: E402
from nsd.synth.skeleton import get_species  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

CHILD = r"""
import json, sys, time
import torch
torch.set_num_threads(1)
from netepu.pipeline.subject_keypoints import invert_export
a = json.loads(sys.argv[1])
t = time.perf_counter()
s = invert_export(a["export"], a["scene"], a["model"], a["out"], **a["kw"])
s["seconds"] = time.perf_counter() - t
print(json.dumps(s))
"""

# the bipeds' cold start in nsd-run: the learned initialiser and two screened templates
BIPEDS = {"initialiser": "builtin", "init_steps": 40, "init_templates": 2}
VARIANTS = [  # (name, masks, invert_export settings)
    ("baseline: cold starts, no occluders", "export", {"occlusion": False}),
    ("occluders, screened template starts", "export", {}),
    ("occluders, 2 templates x 4 headings, unscreened (the stage before)", "export",
     {"templates": 2, "inverse": {"headings": 4}}),
    ("occluders + warm starts (40 steps)", "export", {"warm_steps": 40}),
    ("warm starts (40 steps), no occluders", "export", {"occlusion": False, "warm_steps": 40}),
    ("occluders, 192 points per view", "export", {"inverse": {"points_per_view": 192}}),
    ("occluders, 384 points per view for every start (no point budget; the stage before)",
     "export", {"inverse": {"point_budget": 0}}),
    ("occluders, prune every 10 steps", "export", {"inverse": {"prune_every": 10}}),
    ("learned initialiser, 40 steps (the quadrupeds' default)", "export",
     {"initialiser": "builtin", "init_steps": 40, "init_templates": 0}),
    ("learned initialiser, 40 steps, no heading check (the quadrupeds' default before "
     "2026-12-01)", "export",
     {"initialiser": "builtin", "init_steps": 40, "init_templates": 0, "heading_tolerance": 0}),
    ("learned initialiser, 40 steps, 384 points per view (the quadrupeds' default before "
     "2026-11-30)", "export", {"initialiser": "builtin", "init_steps": 40, "init_templates": 0,
                               "inverse": {"init_points_per_view": 384}}),
    ("learned initialiser, 80 steps", "export",
     {"initialiser": "builtin", "init_steps": 80, "init_templates": 0}),
    ("learned initialiser + 1 screened template, 40 steps", "export",
     {"initialiser": "builtin", "init_steps": 40, "init_templates": 1,
      "inverse": {"init_poses": 16, "init_points_per_view": 384}}),
    ("learned initialiser + 2 screened templates, 60 steps (the default before "
     "2026-11-27 10:00)", "export",
     {"initialiser": "builtin", "init_steps": 60, "init_templates": 2,
      "inverse": {"init_headings": 8, "init_screen_points": 128, "init_point_budget": 768,
                  "init_poses": 16, "init_points_per_view": 384}}),
    ("learned initialiser + 2 templates screened cheaply (4 headings, 64 points) from 16 "
     "poses, point budget 576, 40 steps (the bipeds' default before 2026-11-30)", "export",
     {**BIPEDS,
      "inverse": {"init_headings": 4, "init_screen_points": 64, "init_point_budget": 576,
                  "init_poses": 16, "init_points_per_view": 384}}),
    ("learned initialiser + 2 templates screened cheaply from 16 poses, point budget 448, 40 "
     "steps", "export", {**BIPEDS,
                         "inverse": {"init_point_budget": 448, "init_poses": 16,
                                     "init_points_per_view": 384}}),
    ("learned initialiser + 1 template screened cheaply from 8 poses, at most 288 points per "
     "view, 40 steps (netepu.keypoints.init_templates=1)", "export",
     {"initialiser": "builtin", "init_steps": 40, "init_templates": 1}),
    ("learned initialiser + 2 templates screened cheaply from 16 poses, point budget 576, 30 "
     "steps", "export", {"initialiser": "builtin", "init_steps": 30, "init_templates": 2,
                         "inverse": {"init_poses": 16, "init_points_per_view": 384}}),
    ("learned initialiser + 2 templates screened cheaply from 8 poses, point budget 576, 40 "
     "steps, 384 points per view", "export",
     {**BIPEDS,
      "inverse": {"init_points_per_view": 384}}),
    ("learned initialiser + 2 templates screened cheaply from 8 poses, point budget 576, at "
     "most 288 points per view, 40 steps (the bipeds' default)", "export",
     BIPEDS),
    ("the bipeds' default without the heading check (before 2026-12-01)", "export",
     {**BIPEDS, "heading_tolerance": 0}),
    ("learned initialiser + 2 templates screened cheaply from 8 poses, point budget 576, at "
     "most 288 points per view, 40 steps, the worse starts dropped after 10 steps", "export",
     {**BIPEDS,
      "inverse": {"init_prune": 10}}),
    ("the bipeds' default + warm starts (20 steps)", "export",
     {**BIPEDS, "warm_steps": 20}),
    ("the bipeds' default + warm starts (20 steps at warm_lr 0.01)", "export",
     {**BIPEDS, "warm_steps": 20,
      "inverse": {"warm_lr": 0.01}}),
    ("ground-truth visible masks + occluders", "visible", {}),
    ("ground-truth amodal masks", "amodal", {"occlusion": False}),
]
SMOOTHING = (5.0, 10.0, 20.0)


def _initialiser(kw: dict, species: str) -> dict:
    """``kw`` with ``initialiser: builtin`` replaced by the shipped initialiser's path."""
    if kw.get("initialiser") != "builtin":
        return kw
    return {**kw, "initialiser": str(MODELS / builtin_initialisers()[species]["file"])}


def run_scene(run: Path) -> tuple[str, str]:
    """The scene folder of an ``nsd-run`` folder and the species of its first individual."""
    scene = json.loads((run / "pipeline.json").read_text())["scene"]["summary"]["path"]
    species = json.loads((Path(scene) / "gt" / "scene.json").read_text())[
        "individuals"][0]["species"]
    return scene, species


def truth_export(export: Path, scene: str, out: Path, kind: str) -> None:
    """A copy of ``export`` whose matched rows carry the ground truth's visible or amodal mask
    of their individual (unmatched rows dropped)."""
    from pycocotools import mask as mask_utils

    from nsd.evaluation.identity import ground_truth_identities
    from nsd.io.ground_truth import GroundTruth

    out.mkdir(parents=True, exist_ok=True)
    coco = json.loads((export / "subjects.coco.json").read_text())
    matched = ground_truth_identities(export, scene)
    gt = GroundTruth.load(scene)
    kept = []
    for a in coco["annotations"]:
        if a["id"] not in matched:
            continue
        cam, t, _sid, ident = matched[a["id"]]
        g = gt.frame(cam, t)
        mask = (g.visible if kind == "visible" else g.amodal)[list(g.identity).index(ident)]
        rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
        a["segmentation"] = {"size": rle["size"], "counts": rle["counts"].decode()}
        a["area"] = float(mask.sum())
        kept.append(a)
    coco["annotations"] = kept
    (out / "subjects.coco.json").write_text(json.dumps(coco))


def errors(export: Path, scene: str, keypoints: Path,
           mirror: tuple[int, ...] | None = None) -> dict[str, float]:
    """MPJPE summary and its percentiles over subject-frames; with the species' ``mirror``
    index also the share of subject-frames closer to the truth with left and right swapped
    (a body turned front to back) and the mean MPJPE had each taken the closer of the two.
    The subjects are matched to the ground truth once."""
    from nsd.evaluation.pose import mirror_errors, subject_frame_errors

    if mirror:
        pairs = mirror_errors(export, scene, keypoints, mirror)  # (as fitted, swapped)
        e = [fitted for fitted, _ in pairs]
    else:
        pairs, e = [], subject_frame_errors(export, scene, keypoints)[1]
    mean, median, p25, p75, p90 = ((np.mean(e), *np.percentile(e, [50, 25, 75, 90])) if e
                                   else (np.nan,) * 5)
    out = {"mpjpe_mm": float(mean), "median_mm": float(median), "p25_mm": float(p25),
           "p75_mm": float(p75), "p90_mm": float(p90), "scored": float(len(e))}
    if pairs:
        both = np.array(pairs)
        out["mirrored_share"] = float((both[:, 1] < both[:, 0]).mean())
        out["best_of_mirror_mm"] = float(both.min(1).mean())
    return out


def _rewritten(keypoints: Path, out: Path, change) -> Path:
    """``keypoints3d.npz`` copied to ``out`` with ``change(arrays)`` applied to its arrays."""
    with np.load(keypoints) as z:
        d = dict(z)
    change(d)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **d)
    return out


def unrelabelled(keypoints: Path, mirror: tuple[int, ...], out: Path) -> Path:
    """``keypoints3d.npz`` as fitted: the subject-frames the travel relabelled
    (``subject_relabelled``, :mod:`netepu.pipeline.travel`) swapped back."""
    def back(d: dict) -> None:
        flip = d["subject_relabelled"]
        d["subject_keypoints"] = np.where(flip[:, None, None],
                                          d["subject_keypoints"][:, list(mirror)],
                                          d["subject_keypoints"])
        d["subject_relabelled"] = np.zeros_like(flip)

    return _rewritten(keypoints, out, back)


def smoothed(keypoints: Path, out: Path, sigma: float) -> Path:
    """``keypoints3d.npz`` with its subject keypoints smoothed over time (sigma in frames)."""
    from netepu.pipeline.subject_keypoints import smooth_tracks

    def smooth(d: dict) -> None:
        fits = list(zip(d["subject_frame"].tolist(), d["subject_id"].tolist(),
                        d["subject_keypoints"], d["subject_loss"].tolist(), strict=True))
        d["subject_keypoints"] = np.stack(smooth_tracks(fits, sigma)).astype(np.float32)

    return _rewritten(keypoints, out, smooth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, nargs="+", required=True,
                    help="nsd-run folders of synthetic scenes (several: rows prefixed by the "
                         "run's name)")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: temporary)")
    ap.add_argument("--frame-step", type=int, default=10)
    ap.add_argument("--variants", nargs="+", default=None,
                    help="only these rows (their names; default: every row)")
    ap.add_argument("--baseline-models", type=Path, default=None,
                    help="a models folder (e.g. the previous shipped models): the rows again "
                         "with its model, named '... [baseline model]'")
    ap.add_argument("--report", default="keypoints", help="name of the report file")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-keypoints-"))
    chosen = [v for v in VARIANTS if args.variants is None or v[0] in args.variants]
    if args.variants is not None and len(chosen) != len(args.variants):
        raise SystemExit(f"--variants: choose from {[v[0] for v in VARIANTS]}")
    jobs, exports, scenes = [], {}, {}  # (row name, run, masks, invert_export settings, model)
    mirrors = {}  # run -> its species' left/right index
    for run in args.run:
        scene, species = run_scene(run)
        scenes[run] = scene
        mirrors[run] = get_species(species).mirror_index()
        exports[run, "export"] = run / "export"
        for kind in ("visible", "amodal"):
            if any(masks == kind for _, masks, _ in chosen):
                exports[run, kind] = work / f"{run.name}_truth_{kind}"
                truth_export(exports[run, "export"], scene, exports[run, kind], kind)
        prefix = f"{run.name}: " if len(args.run) > 1 else ""
        jobs += [(prefix + name, run, masks, _initialiser(kw, species), MODELS / f"{species}.pt")
                 for name, masks, kw in chosen]
        if args.baseline_models is not None:
            jobs += [(f"{prefix}{name} [baseline model]", run, masks, _initialiser(kw, species),
                      args.baseline_models / f"{species}.pt") for name, masks, kw in chosen]
    cores = sorted(os.sched_getaffinity(0))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    rows, outs = [], {}
    for first in range(0, len(jobs), len(cores)):  # one job per core at a time
        batch = []
        for cpu, (name, run, masks, kw, model) in zip(cores, jobs[first:first + len(cores)],
                                                      strict=False):  # the last may be short
            outs[name] = work / f"variant{len(outs)}"
            arg = {"export": str(exports[run, masks]), "scene": scenes[run], "model": str(model),
                   "out": str(outs[name]), "kw": {"frame_step": args.frame_step, **kw}}
            batch.append((name, run, masks, subprocess.Popen(
                ["taskset", "-c", str(cpu), sys.executable, "-c", CHILD, json.dumps(arg)],
                stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)))
        for name, run, masks, proc in batch:
            text, _ = proc.communicate()
            if proc.returncode:
                raise SystemExit(f"{name}: the inversion failed")
            s = json.loads(text.strip().splitlines()[-1])
            rows.append({"variant": name,
                         **errors(exports[run, masks], scenes[run],
                                  outs[name] / "keypoints3d.npz", mirrors[run]),
                         "s_per_subject_frame": s["seconds"] / max(1, s["subject_frames"]),
                         "warm_share": s.get("warm_share"), "mean_loss": s["mean_loss"],
                         "travel_relabelled": s.get("travel_relabelled"),
                         "heading_refits": s.get("heading_refits"),
                         "heading_turned": s.get("heading_turned")})
            print(rows[-1], flush=True)
            if s.get("travel_relabelled") and not kw.get("smooth_frames"):
                path = unrelabelled(outs[name] / "keypoints3d.npz", mirrors[run],
                                    work / f"untravelled{len(outs)}" / "keypoints3d.npz")
                rows.append({"variant": f"{name} [travel off]",
                             **errors(exports[run, masks], scenes[run], path, mirrors[run]),
                             "travel_relabelled": 0})
                print(rows[-1], flush=True)
    occ = outs.get("occluders, screened template starts")  # one run only
    run = args.run[0]
    for sigma in SMOOTHING if occ is not None and args.variants is None else ():
        path = smoothed(occ / "keypoints3d.npz", work / f"smooth{sigma:g}" / "keypoints3d.npz",
                        sigma)
        rows.append({"variant": f"occluders, smoothed (sigma {sigma:g} frames)",
                     **errors(exports[run, "export"], scenes[run], path)})
    write_report(
        args.report, "Label-free keypoints from the pipeline's masks", rows,
        notes=("Runs " + ", ".join(f"`{r.name}` (scene `{Path(scenes[r]).name}`)" for r in args.run)
               + f", every "
               f"{args.frame_step}th exported frame, every subject seen in >= 2 cameras, the "
               "shipped geometry model of the scene's species"
               + (f" (rows marked [baseline model]: `{args.baseline_models}`)"
                  if args.baseline_models else "")
               + f"; one process per row, one torch thread ({len(cores)} row(s) at a "
               f"time on {len(cores)} core(s), so seconds are comparable across rows, not with "
               "a machine at rest). MPJPE in mm against the scene's 3D keypoints; percentiles "
               "over subject-frames. Ground-truth rows: the same rows' masks replaced by the "
               "ground truth's visible (or amodal) masks of their matched individual, the "
               "floor the masks leave. Smoothing rows: the occlusion-aware fits smoothed "
               "afterwards (netepu.keypoints.smooth_frames)."),
    )


if __name__ == "__main__":
    main()
