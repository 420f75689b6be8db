"""Identities from texture codes on synthetic scenes with occlusion: label-free vs true keypoints.

    .venv/bin/python tools/bench_reid_scenes.py one --n 2 --minutes 10   # scene + nsd-run + scores
    .venv/bin/python tools/bench_reid_scenes.py one --n 3 --minutes 10
    .venv/bin/python tools/bench_reid_scenes.py rescore     # score the stored runs again
    .venv/bin/python tools/bench_reid_scenes.py report      # docs/benchmarks/reid_scenes.{md,json}
    .venv/bin/python tools/bench_reid_scenes.py keypoints --run runs/kp_three \
        --scene /tmp/scene3 --n 3 --tag three   # an existing nsd-run folder, shipped models
    .venv/bin/python tools/bench_reid_scenes.py keypoints-report  # reid_keypoints.{md,json}

For N = 2 and 3 bipeds in close interaction (4 studio cameras, 300 frames at
128 x 128), every individual wears a generated texture (ids >= 100) that the
texture model never saw: it was trained on the 16 textures of the fixed pool.
``nsd-run`` then runs the whole pipeline on the unlabeled footage: NSD trained
with N windows, evaluation, export, label-free 3D keypoints by NeTePu inverse
rendering of each subject's visible masks in the 4 views (every
``--frame-step`` frames), texture codes from the visible pixels, identities of
the tracks. The texture codes are computed a second time for the same rows from
the ground-truth 3D keypoints of the individual each row matches, so that the
two columns differ only in the keypoints that place the NNOPCS maps.

Scores (rows = exported subject-camera-frames with a texture code in both
variants that match a ground-truth visible mask at IoU >= 0.5):

* ``mask_miou``, ``detection_rate``: nsd-eval on the held-out frames;
* ``count_accuracy``: frames whose exported subjects (distinct track ids) number N;
* ``mpjpe_mm``: the label-free keypoints against the ground truth;
* ``cross_view_rank1``: for each row, its nearest row (cosine of texture
  codes) among the rows of the same frame in the other cameras belongs to the
  same individual; ``cross_time_rank1``: the same among rows of the same camera
  ten or more frames away; ``chance``: 1 / N;
* ``identity_accuracy`` and its cross-view / cross-time pair accuracies: the
  pipeline's identities (each row by its own texture code, :mod:`netepu.reid.identities`)
  scored on those rows; ``tracks_identity_accuracy``: each row its track's identity
  (tracks grouped by their mean texture code), on the same rows.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import write_report  # noqa: E402

WORK = Path("/tmp/nsd-bench-reid")
KEYPOINT_WORK = ROOT / "runs" / "reid_keypoints"
GEOMETRY = ROOT / "runs/netepu/geometry_biped/checkpoint.pt"
TEXTURES = {  # texture models (netepu-train stage=texture), all trained on the 16 pool textures
    "cross-view": ROOT / "runs/netepu/texture_full_xv/checkpoint.pt",
    "cross-view + contrastive": ROOT / "runs/netepu/texture_full_xv_contrast/checkpoint.pt",
    "cross-view + contrastive + normals": ROOT / "runs/netepu/texture_w02_normals/checkpoint.pt",
    "cross-view + contrastive + normals, whitened": ROOT
    / "runs/netepu/texture_w02_normals_whitened/checkpoint.pt",
    "cross-view + contrastive + normals, whitened with colour statistics": ROOT
    / "runs/netepu/texture_w02_normals_colour/checkpoint.pt",
}
KEYPOINT_VARIANTS = {  # netepu.keypoints.source -> the row's name
    "inverse": "label-free keypoints",
    "regressor": "regressor keypoints (10 % of frames labelled)",
}
FIRST_UNSEEN_TEXTURE = 100  # ids >= the pool size are generated textures, never in the pool


def rank1(codes: np.ndarray, ident: np.ndarray, candidates: np.ndarray) -> float:
    """Share of rows whose nearest candidate (cosine) has their identity.

    Args:
        codes: (R, D); ident: (R,); candidates: (R, R) bool, row i may retrieve row j.
    """
    from nsd.evaluation.reid import nearest_candidates

    best = nearest_candidates(codes, candidates)
    has = best >= 0
    return float((ident[best] == ident)[has].mean()) if has.any() else float("nan")


def _gt_keypoints(export: Path, scene: Path, label_free: Path, out: Path) -> None:
    """Ground-truth keypoints (npz id, keypoints) for the rows the label-free file covers."""
    from nsd.evaluation.identity import ground_truth_identities
    from nsd.io.ground_truth import GroundTruth

    truth = GroundTruth.load(scene).scene.keypoints3d
    matched = ground_truth_identities(export, scene)
    with np.load(label_free) as z:
        ids = [int(i) for i in z["id"] if int(i) in matched]
    kps = [truth[matched[i][3]][matched[i][1]] for i in ids]
    np.savez(out, id=np.array(ids, np.int64), keypoints=np.stack(kps).astype(np.float32))


def _scores(
    export: Path, scene: Path, tables: dict[str, Path], n: int, column: str = "texture"
) -> dict[str, dict]:
    """Row-level rank-1 and pipeline identity accuracy of each table's ``column`` (the codes
    or their re-id embeddings), on the rows coded in every table."""
    from netepu.reid.identities import assign_identities
    from nsd.evaluation.identity import ground_truth_identities, identity_accuracy
    from nsd.io.embeddings import read_embeddings

    matched = ground_truth_identities(export, scene)
    cols = ["id", "camera", "subject_id", "frame", column, "texture_valid"]
    read = {k: read_embeddings(p, cols) for k, p in tables.items()}
    ids = next(iter(read.values()))["id"]
    common = np.isin(ids, list(matched))
    for t in read.values():
        assert np.array_equal(t["id"], ids), "tables differ in row order"
        common &= t["texture_valid"].astype(bool)
    rows = ids[common]
    ident = np.array([matched[int(i)][3] for i in rows])
    cams = np.array([matched[int(i)][0] for i in rows])
    frames = np.array([matched[int(i)][1] for i in rows])
    cross_view = (frames[:, None] == frames[None]) & (cams[:, None] != cams[None])
    cross_time = (cams[:, None] == cams[None]) & (np.abs(frames[:, None] - frames[None]) >= 10)
    out = {}
    for name, t in read.items():
        codes = t[column][common].astype(np.float64)
        sub = {k: t[k][common] for k in ("id", "camera", "subject_id", "frame", column)}
        out[name] = {
            "rows": int(common.sum()),
            "cross_view_rank1": rank1(codes, ident, cross_view),
            "cross_time_rank1": rank1(codes, ident, cross_time),
        }
        for method in ("rows", "tracks"):  # both scored on the same rows
            identity, summary = assign_identities(sub, column, n, method)
            acc = identity_accuracy(export, scene, rows, identity)
            tag = "" if method == "rows" else "tracks_"
            out[name] |= {f"{tag}{k}": v for k, v in acc.items() if k != "matched_rows"}
            out[name]["tracks"] = summary["tracks"]
    return out


def _count_accuracy(export: Path, n: int) -> float:
    coco = json.loads((export / "subjects.coco.json").read_text())
    frame_of = {int(im["id"]): int(im["frame"]) for im in coco["images"]}
    per_frame: dict[int, set] = {t: set() for t in frame_of.values()}
    for a in coco["annotations"]:
        per_frame[frame_of[int(a["image_id"])]].add(int(a["subject_id"]))
    return float(np.mean([len(s) == n for s in per_frame.values()]))


def one(
    n: int, minutes: float, frame_step: int, threads: int, texture_name: str, source: str
) -> None:
    import torch

    from netepu.pipeline.embed import embed_into_copy
    from netepu.pipeline.run import load_run_config, run_pipeline

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    torch.set_num_threads(threads)
    scene, run = WORK / f"scene{n}", WORK / f"run{n}"
    suffix = "" if source == "inverse" else f"_{source}"
    if suffix and not run.with_name(run.name + suffix).is_dir() and run.is_dir():
        shutil.copytree(run, run.with_name(run.name + suffix))  # reuse its training and export
    run = run.with_name(run.name + suffix)
    texture = TEXTURES[texture_name]
    textures = [FIRST_UNSEEN_TEXTURE + 7 * n + i for i in range(n)]
    if not (scene / "gt").is_dir():  # an existing scene is kept: nsd-run then reuses its stages
        subprocess.run(
            [
                str(ROOT / ".venv/bin/nsd-synth"),
                f"out={scene}",
                f"num_individuals={n}",
                f"texture_ids={textures}".replace(" ", ""),
                f"seed={n}",
                "overwrite=true",
            ],
            check=True,
        )
    cfg = load_run_config(
        f"scene={scene}",
        f"out={run}",
        f"threads={threads}",
        "train.trainer.progress=false",
        "+export.progress=false",
        f"train.model.num_windows={n}",
        "~train.data.same_view",  # Bi-NVS pairs only, as when these rows were first measured
        "train.model.mode=bi_nvs",
        f"train.trainer.max_minutes={minutes}",
        f"netepu.geometry={GEOMETRY}",
        f"netepu.texture={texture}",
        f"netepu.keypoints.frame_step={frame_step}",
        f"netepu.keypoints.source={source}",
        f"netepu.identities.k={n}",
    )
    t0 = time.perf_counter()
    results = run_pipeline(cfg)
    seconds = {k: round(r.seconds, 1) for k, r in results.items()}
    export = results["export"].folder
    label_free = results["keypoints"].folder / "keypoints3d.npz"
    gt_kp = WORK / f"gt_keypoints{n}{suffix}.npz"
    _gt_keypoints(export, scene, label_free, gt_kp)
    gt_dir = WORK / f"texture_gt{n}{suffix}"
    shutil.rmtree(gt_dir, ignore_errors=True)
    t1 = time.perf_counter()
    embed_into_copy(export, gt_dir, texture, gt_kp, scene)
    seconds["texture (ground-truth keypoints)"] = round(time.perf_counter() - t1, 1)
    from nsd.io.embeddings import embeddings_path

    tables = {
        KEYPOINT_VARIANTS[source]: embeddings_path(results["texture"].folder),
        "ground-truth keypoints": embeddings_path(gt_dir),
    }
    ev = results["evaluate"].summary.get("metrics", {})
    record = {
        "individuals": n,
        "texture_model": texture_name,
        "textures": textures,
        "minutes": minutes,
        "frame_step": frame_step,
        "training_steps": results["train"].summary.get("steps"),
        "mask_miou": ev.get("mask_miou"),
        "detection_rate": ev.get("detection_rate"),
        "count_accuracy": _count_accuracy(export, n),
        "keypoints_source": source,
        "keypoints": results["keypoints"].summary.get("accuracy", {}),
        "regressor": results["keypoints"].summary.get("regressor"),
        "column": "texture_reid",
        "scores": _scores(export, scene, tables, n, "texture_reid"),
        "seconds": seconds,
        "total_seconds": round(time.perf_counter() - t0, 1),
    }
    tag = "" if texture_name == "cross-view" else "_" + re.sub(r"\W+", "_", texture_name)
    tag += suffix
    (WORK / f"result{n}{tag}.json").write_text(json.dumps(record, indent=1, default=float))
    print(json.dumps(record, indent=1, default=float))


def rescore() -> None:
    """Recompute the scores of every result file from its stored export and tables."""
    from nsd.io.embeddings import embeddings_path

    for path in sorted(WORK.glob("result*.json")):
        r = json.loads(path.read_text())
        n, source = r["individuals"], r.get("keypoints_source", "inverse")
        suffix = "" if source == "inverse" else f"_{source}"
        tables = {
            KEYPOINT_VARIANTS[source]: embeddings_path(WORK / f"run{n}{suffix}" / "texture"),
            "ground-truth keypoints": embeddings_path(WORK / f"texture_gt{n}{suffix}"),
        }
        r["scores"] = _scores(  # mu is the same in every table of one model's weights
            WORK / f"run{n}{suffix}" / "export",
            WORK / f"scene{n}",
            tables,
            n,
            r.get("column", "texture"),
        )
        path.write_text(json.dumps(r, indent=1, default=float))
        print(path.name, json.dumps(r["scores"], indent=1, default=float))


def report() -> None:
    import torch

    torch.set_num_threads(1)  # the header states the threads of the runs (`one --threads 1`)
    rows, records = [], []
    for path in sorted(WORK.glob("result*.json")):
        r = json.loads(path.read_text())
        records.append(r)
        for variant, s in r["scores"].items():
            rows.append(
                {
                    "individuals": r["individuals"],
                    "texture model": r.get("texture_model", "cross-view"),
                    "compared": r.get("column", "texture"),
                    "keypoints": variant,
                    "mask mIoU": r["mask_miou"],
                    "detection rate": r["detection_rate"],
                    "count accuracy": r["count_accuracy"],
                    "MPJPE mm": r["keypoints"].get("mpjpe_mm")
                    if not variant.startswith("ground")
                    else "",
                    "rows": s["rows"],
                    "cross-view rank-1": s["cross_view_rank1"],
                    "cross-time rank-1": s["cross_time_rank1"],
                    "chance": 1 / r["individuals"],
                    "identity accuracy": s.get("identity_accuracy"),
                    "cross-view pairs": s.get("cross_view_accuracy"),
                    "cross-time pairs": s.get("cross_time_accuracy"),
                    "identity accuracy, per track": s.get("tracks_identity_accuracy"),
                    "train steps": r["training_steps"],
                }
            )
    notes = (ROOT / "tools/bench_reid_scenes.notes.md").read_text()
    write_report(
        "reid_scenes",
        "Identities from texture codes on synthetic scenes with occlusion",
        rows,
        notes,
        extra={
            "runs": records,
            "geometry": str(GEOMETRY.relative_to(ROOT)),
            "textures": {k: str(v.relative_to(ROOT)) for k, v in TEXTURES.items()},
        },
    )


def keypoints(run: Path, scene: Path, n: int, tag: str) -> None:
    """Identities of an existing ``nsd-run`` folder (the shipped models, its label-free
    keypoints) against the same rows coded from the ground-truth keypoints."""
    from netepu.pipeline.embed import embed_into_copy
    from netepu.pipeline.species_models import MODELS, scene_species
    from nsd.io.embeddings import embeddings_path

    stages = json.loads((run / "pipeline.json").read_text())
    species = scene_species(scene)
    if len(species) != 1:
        raise SystemExit(f"{scene}: one species expected, found {species}")
    texture = MODELS / f"{species[0]}.pt"  # what the run's texture stage used (built in)
    export = run / "export"
    out = KEYPOINT_WORK / tag
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    gt_kp = out / "gt_keypoints.npz"
    _gt_keypoints(export, scene, run / "keypoints" / "keypoints3d.npz", gt_kp)
    t0 = time.perf_counter()
    embed_into_copy(export, out / "texture_gt", texture, gt_kp, scene)
    tables = {
        "label-free keypoints": embeddings_path(run / "texture"),
        "ground-truth keypoints": embeddings_path(out / "texture_gt"),
    }
    kp = stages["keypoints"]["summary"]
    textures = [int(i["texture_id"]) for i in
                json.loads((scene / "gt" / "scene.json").read_text())["individuals"]]
    record = {
        "run": str(run), "species": species[0], "individuals": n, "texture_ids": textures,
        "mpjpe_mm": kp["accuracy"]["mpjpe_mm"],
        "mpjpe_mm_median": kp["accuracy"]["mpjpe_mm_median"],
        "subject_frames": kp["subject_frames"],
        "seconds_per_subject_frame": kp["seconds_per_subject_frame"],
        "scores": _scores(export, scene, tables, n, "texture_reid"),
        "ground_truth_texture_seconds": round(time.perf_counter() - t0, 1),
    }  # fmt: skip
    (KEYPOINT_WORK / f"result_{tag}.json").write_text(json.dumps(record, indent=1, default=float))
    print(json.dumps(record, indent=1, default=float))


def _texture_kind(ids: list[int] | None) -> str:
    """``pool``, ``never seen`` or ``mixed`` for a scene's texture ids (records before the
    ids were stored: pool)."""
    unseen = [i >= FIRST_UNSEEN_TEXTURE for i in ids or []]
    return "never seen" if unseen and all(unseen) else "mixed" if any(unseen) else "pool"


def keypoints_report() -> None:
    rows, records = [], {}
    for path in sorted(KEYPOINT_WORK.glob("result_*.json")):
        r = json.loads(path.read_text())
        records[path.stem[len("result_"):]] = r
        for variant, s in r["scores"].items():
            free = variant.startswith("label")
            rows.append({
                "scene": path.stem[len("result_"):], "species": r.get("species", "biped"),
                "individuals": r["individuals"],
                "textures": _texture_kind(r.get("texture_ids")),
                "keypoints": variant,
                "MPJPE mean / median (mm)": (
                    f"{r['mpjpe_mm']:.1f} / {r['mpjpe_mm_median']:.1f}" if free else "0"),
                "rows": s["rows"], "cross-view rank-1": round(s["cross_view_rank1"], 4),
                "cross-time rank-1": round(s["cross_time_rank1"], 4),
                "identity accuracy": round(s["identity_accuracy"], 4),
                "identity accuracy, per track": round(s["tracks_identity_accuracy"], 4),
                "chance": round(1 / r["individuals"], 4),
            })  # fmt: skip
    notes = (
        "Each scene is an existing `nsd-run` folder (the built-in NeTePu models for the "
        "keypoints and the texture codes; label-free keypoints from the run's inversion of "
        "the exported visible masks with the keypoint settings of its day, in its "
        "`pipeline.json`; the scene's species' model). `ground-truth keypoints` "
        "codes the same exported rows "
        "again (`netepu.pipeline.embed.embed_into_copy`) with the true 3D keypoints of the "
        "individual each row matches, so the two rows of a scene differ only in the keypoints "
        "that place the NNOPCS maps. Scored on the rows coded in both and matched to a "
        "ground-truth visible mask (IoU >= 0.5); identities by `texture_reid` "
        "(`tools/bench_reid_scenes.py keypoints`, docstring of `_scores`). `textures`: "
        "`pool` where the individuals wear textures of the 16-texture pool the texture model "
        f"was trained on (the scenes' default `texture_ids: null`), `never seen` where every "
        f"one wears a generated texture (id >= {FIRST_UNSEEN_TEXTURE}) that no model saw."
    )
    write_report("reid_keypoints",
                 "Identities from texture codes: label-free against ground-truth keypoints",
                 rows, notes, extra={"runs": records})  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    k = sub.add_parser("keypoints", help="an existing nsd-run folder: label-free vs true keypoints")
    k.add_argument("--run", type=Path, required=True)
    k.add_argument("--scene", type=Path, required=True)
    k.add_argument("--n", type=int, required=True)
    k.add_argument("--tag", required=True)
    sub.add_parser("keypoints-report", help="docs/benchmarks/reid_keypoints.{md,json}")
    o = sub.add_parser("one")
    o.add_argument("--n", type=int, required=True)
    o.add_argument("--minutes", type=float, default=10.0, help="NSD training minutes")
    o.add_argument("--frame-step", type=int, default=15, help="invert every this many frames")
    o.add_argument("--threads", type=int, default=1)
    o.add_argument("--texture", choices=sorted(TEXTURES), default="cross-view")
    o.add_argument("--keypoints", choices=sorted(KEYPOINT_VARIANTS), default="inverse")
    sub.add_parser("rescore", help="score the stored runs again (e.g. new identity code)")
    sub.add_parser("report")
    args = ap.parse_args()
    if args.cmd == "keypoints":
        KEYPOINT_WORK.mkdir(parents=True, exist_ok=True)
        keypoints(args.run, args.scene, args.n, args.tag)
    elif args.cmd == "keypoints-report":
        keypoints_report()
    elif args.cmd == "one":
        WORK.mkdir(parents=True, exist_ok=True)
        one(args.n, args.minutes, args.frame_step, args.threads, args.texture, args.keypoints)
    elif args.cmd == "rescore":
        rescore()
    else:
        report()


if __name__ == "__main__":
    main()
