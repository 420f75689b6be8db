"""Count accuracy: does NSD with an upper bound of 4 windows find how many individuals there are?

    python tools/bench_count.py one --n 2 --minutes 5 --presence hull   # scene + training + counts
    python tools/bench_count.py report                     # docs/benchmarks/count.{md,json}

For N = 1..4 individuals, a synthetic scene (4 studio cameras, 96 x 96, 300
frames, close interaction) is written with nsd-synth and nsd-train trains on it
with ``model.num_windows=4``, the learned window presence on
(``model.detector.presence=true``) and presence learned from a label-free target
(``--presence``: the ``prior_presence`` group, ``hull`` or ``marginal``,
:mod:`nsd.priors.presence`), only the windows that are on in the image loss,
everything else at the defaults (``--extra`` overrides are in the variant column).
Counts are measured on 30 frames spread over the sequence (the transductive
use; no labels are used in training):

* ``frame_count_accuracy``: the number of distinct cross-view subject ids of the
  active windows of a frame (all 4 views; ids from the model's association, as
  nsd-export assigns them) equals N;
* ``view_count_accuracy``: the active windows of one camera-frame equal the
  individuals visible in it (ground-truth visible area >= 4 pixels);
* ``mean_active_windows`` per camera-frame, ``scene_count`` (median frame count),
  the mean presence of the windows sorted from most to least present;
* ``detection_rate`` and ``mask_miou`` (nsd-eval's definitions) on the same frames;
* ``hull frame count accuracy (no training)``: the same, for the individuals the
  label-free multi-view visual hull alone finds per frame (:mod:`nsd.cues.occupancy`,
  ``split=False``): what the count would be without NSD;
* ``background ghost %``: per camera, the share of pixels where the median
  background differs from the true backdrop (an individual that stood still long
  enough stays in the median, and there the foreground evidence is lost);
* identities: every frame exported (``nsd-export``), tracks grouped into identities
  by NSD's appearance vectors with the label-free count (``netepu.identities``; no
  texture model here), scored as in ``nsd.evaluation.identity.identity_accuracy``.

Run ``one`` for each N (one core each, e.g. ``taskset -c 1``), then ``report``.
``rescore`` measures every trained run again with the current code (the checkpoints
are kept; after a change to inference or to the cross-view association).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.benchlib import markdown_table, write_report

WORK = Path("/tmp/nsd-bench-count")
SCENE = ["image_size=[96,96]", "num_frames=300"]
TRAIN = [
    "data.image_size=[96,96]",
    "model.num_windows=4",
    "model.detector.presence=true",
    "trainer.max_steps=0",
    "trainer.checkpoint_every=0",
    "trainer.progress=false",
    "eval_frames=10",
]
FRAMES = 30


def count_metrics(checkpoint: Path, scene: Path, n: int, frames: int = FRAMES) -> dict:
    """Count figures of a trained decomposition on ``frames`` frames spread over ``scene``."""
    from types import SimpleNamespace

    import torch

    from nsd.evaluation.decomposition import evaluate_model
    from nsd.inference.association_scores import association_scores
    from nsd.inference.single import associate_views, decompose
    from nsd.io.ground_truth import GroundTruth
    from nsd.io.scene_data import SceneData
    from nsd.model.checkpoint import load_decomposition

    trained = load_decomposition(checkpoint)
    H, W = trained.frame_hw
    data = SceneData(scene, (W, H), val_fraction=0.0)
    gt = GroundTruth.load(scene)
    model = trained.model
    dims = int(model.cfg.association_dims)
    idx = np.linspace(0, len(data.frames) - 1, frames).round().astype(int)
    frame_counts, view_ok, active_n, presence = [], [], [], []
    for t in idx.tolist():
        views, bgs = data.views(t)
        dec = decompose(model, views, bgs)
        one = SimpleNamespace(windows=dec.windows, app=dec.app)

        def score(v: int, r: int, one=one) -> torch.Tensor:
            return association_scores(model, one, data.cameras, (H, W), v, r)

        ids = associate_views(dec.app, dec.active, dims, score)
        frame_counts.append(len(set(ids[ids >= 0].tolist())))
        for v, cam in enumerate(data.rig.names):
            visible = visible_count(gt, cam, t, (H, W))
            act = int(dec.active[v].sum())
            view_ok.append(act == visible)
            active_n.append(act)
        presence.append(dec.presence.sort(-1, descending=True).values.mean(0).numpy())
    ev = evaluate_model(model, data, idx, gt)
    fc = np.asarray(frame_counts)
    ghost = background_ghosts(data, gt)
    return {
        "individuals": n,
        "steps": int(trained.step),
        "frame_count_accuracy": float((fc == n).mean()),
        "frame_count_mae": float(np.abs(fc - n).mean()),
        "scene_count": float(np.median(fc)),
        "view_count_accuracy": float(np.mean(view_ok)),
        "mean_active_windows": float(np.mean(active_n)),
        "presence_sorted": [round(float(p), 3) for p in np.mean(presence, 0)],
        "detection_rate": float(ev["detection_rate"]),
        "mask_miou": float(ev["mask_miou"]),
        "background_ghost_percent": ghost,
    }


def visible_count(gt, cam: str, t: int, size: tuple[int, int]) -> int:
    """Individuals visible in a camera-frame of the ground truth (visible area >= 4 px)."""
    g = gt.frame(cam, t, size)
    return int((g.visible.reshape(len(g.visible), -1).sum(1) >= 4).sum())


def _hull_data(scene: Path, frames: int = 0):
    """The scene at the benchmark's size (``frames`` spread over it, as in
    :func:`count_metrics`; 0: all) with its multi-view hull proposals for an upper bound
    of 4, not split (``split=False``)."""
    import torch
    from hydra import compose, initialize_config_module

    from nsd.io.scene_data import SceneData

    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose("train", overrides=[f"data.scene={scene}", *TRAIN])
    H, W = cfg.data.image_size[1], cfg.data.image_size[0]
    data = SceneData(scene, (W, H), val_fraction=0.0)
    if frames:
        idx = np.linspace(0, len(data.frames) - 1, frames).round().astype(int)
        data.frames = data.frames[torch.from_numpy(idx)]
    data.compute_multiview_proposals(
        4,
        cfg.loss.evidence_threshold,
        cfg.loss.evidence_softness,
        resolution=cfg.prior_proposal.resolution,
        split=False,
        min_views=cfg.prior_proposal.min_views,
        owners=False,  # counts only; the frames here are a tensor, not the frame store
    )
    return data


def hull_count(scene: Path, n: int, frames: int = FRAMES) -> dict:
    """The label-free count of the multi-view visual hull alone (no training): per frame,
    the individuals :func:`nsd.cues.occupancy.multiview_proposals` finds with an upper bound
    of 4 (``split=False``), on the same frames as :func:`count_metrics`."""
    data = _hull_data(scene, frames)
    counts = data.proposal_valid.any(1).sum(-1).numpy()
    return {
        "hull_frame_count_accuracy": float((counts == n).mean()),
        "hull_scene_count": float(np.median(counts)),
    }


COUNT_SETTINGS = {  # the hull target's count settings: (count_window, count_population)
    "per frame": (1, "frame"),
    "median 31": (31, "frame"),
    "median 31 + scene population": (31, "scene"),
}


def hull_target_accuracy(scene: Path) -> dict:
    """Per count setting, the share of camera-frames (all frames) where the hull target's
    count (:func:`nsd.priors.presence.smoothed_counts`) equals the individuals visible in the
    ground truth (visible area >= 4 pixels): how right the label-free target is."""
    from nsd.io.ground_truth import GroundTruth
    from nsd.priors.presence import smoothed_counts

    data = _hull_data(scene)
    gt = GroundTruth.load(scene)
    visible = np.array(
        [
            [visible_count(gt, cam, t, data.frame_hw) for cam in data.rig.names]
            for t in range(len(data.frames))
        ]
    )
    out = {}
    for name, (window, population) in COUNT_SETTINGS.items():
        c = smoothed_counts(data.proposal_valid, window, population == "scene").numpy()
        out[name] = float((c == visible).mean())
    return out


def background_ghosts(data, gt) -> list[float]:
    """Per camera, the % of pixels where the median background the model uses differs
    from the true backdrop by more than 30/255 in a channel (individuals that stood
    still long enough to stay in the median)."""
    import cv2

    H, W = data.backgrounds.shape[-2:]
    out = []
    for v, cam in enumerate(data.rig.names):
        true = cv2.resize(gt.scene.background(cam)[0], (W, H), interpolation=cv2.INTER_AREA)
        used = (data.backgrounds[v].permute(1, 2, 0).numpy() * 255).round()
        out.append(round(float((np.abs(used - true).max(-1) > 30).mean() * 100), 2))
    return out


def identities(checkpoint: Path, scene: Path, out: Path, overwrite: bool = False) -> dict:
    """Export every frame, group the tracks into identities by NSD's appearance vectors
    (``netepu.identities``, label-free k) and score them against the ground truth."""
    from netepu.reid.identities import assign_identities
    from nsd.evaluation.identity import identity_accuracy
    from nsd.export.config import load_export_config
    from nsd.export.subjects import export_subjects
    from nsd.io.embeddings import read_embeddings

    cfg = load_export_config(
        checkpoint=str(checkpoint),
        scene=str(scene),
        out=str(out),
        overwrite=overwrite,
        **{"views.tensorboard": False, "views.tsne": False, "progress": False},
    )
    export_subjects(cfg)
    table = read_embeddings(out, ["id", "subject_id", "frame", "app"])
    identity, summary = assign_identities(table, "app", method="tracks")
    acc = identity_accuracy(out, scene, table["id"], identity)
    return {
        "identity_k": summary["k"],
        "tracks": summary["tracks"],
        **{f"id_{k}": v for k, v in acc.items()},
    }


def one(n: int, minutes: float, extra: list[str], presence: str = "marginal") -> dict:
    """Write the N-individual scene (once), train on it, measure counts; saves result.json."""
    import torch
    from hydra import compose, initialize_config_module

    from nsd.synth.cli import run as synth
    from nsd.training.train import train

    torch.set_num_threads(1)
    scene = WORK / f"scene{n}"
    if not (scene / "gt" / "scene.json").is_file():
        synth(
            {
                "out": str(scene),
                "overwrite": True,
                "num_individuals": n,
                **{k: json.loads(v) for k, v in (s.split("=", 1) for s in SCENE)},
            }
        )
    tag = f"n{n}-{presence}" + ("-" + "-".join(e.replace("=", "_") for e in extra) if extra else "")
    run_dir = WORK / tag
    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"data.scene={scene}",
                f"trainer.max_minutes={minutes}",
                *TRAIN,
                f"prior_presence={presence}",
                *extra,
            ],
        )
    t0 = time.perf_counter()
    train(cfg, run_dir)
    info = {"minutes": minutes, "presence": presence, "overrides": extra}
    return score_run(run_dir, n, {**info, "wall_seconds": time.perf_counter() - t0})


def score_run(run_dir: Path, n: int, info: dict, overwrite: bool = False) -> dict:
    """Count and identity figures of a trained run, written to its result.json (the count
    figures first, so that they survive a failing export)."""
    scene = WORK / f"scene{n}"
    res = {**count_metrics(run_dir / "checkpoint.pt", scene, n), **info}
    path = run_dir / "result.json"
    path.write_text(json.dumps(res, indent=2))
    try:
        res.update(identities(run_dir / "checkpoint.pt", scene, run_dir / "export", overwrite))
    except Exception as e:  # the count figures above are kept
        res["identities_error"] = repr(e)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(res, indent=2))
    tmp.replace(path)
    print(run_dir.name, json.dumps(res), flush=True)
    return res


def rescore(only: list[str]) -> None:
    """Count and identity figures of every trained run (or those named), measured again."""
    import torch

    torch.set_num_threads(1)
    for f in sorted(WORK.glob("n*/result.json")):
        if only and f.parent.name not in only:
            continue
        old = json.loads(f.read_text())
        keep = ("minutes", "presence", "overrides", "wall_seconds")
        score_run(f.parent, old["individuals"], {k: old[k] for k in keep if k in old}, True)


def report() -> None:
    rows = []
    hull = {}
    for f in sorted(WORK.glob("n*/result.json")):
        r = json.loads(f.read_text())
        n = r["individuals"]
        if n not in hull:  # the scene's hull count, kept next to the scene
            cached = WORK / f"scene{n}" / "hull_count.json"
            if not cached.is_file():
                cached.write_text(json.dumps(hull_count(WORK / f"scene{n}", n)))
            hull[n] = json.loads(cached.read_text())
        base = "prior_presence=" + r.get("presence", "marginal")
        rows.append(
            {
                "individuals": r["individuals"],
                "variant": " ".join([base, *r["overrides"]]),
                "minutes": r["minutes"],
                "steps": r["steps"],
                "frame_count_accuracy": round(r["frame_count_accuracy"], 3),
                "hull frame count accuracy (no training)": round(
                    hull[n]["hull_frame_count_accuracy"], 3
                ),
                "frame_count_mae": round(r["frame_count_mae"], 3),
                "scene_count": r["scene_count"],
                "view_count_accuracy": round(r["view_count_accuracy"], 3),
                "mean_active_windows": round(r["mean_active_windows"], 2),
                "presence_sorted": " / ".join(f"{p:.2f}" for p in r["presence_sorted"]),
                "detection_rate": round(r["detection_rate"], 3),
                "mask_miou": round(r["mask_miou"], 3),
                "background ghost %": " / ".join(
                    f"{g:.1f}" for g in r.get("background_ghost_percent", [])
                ),
                "tracks": r.get("tracks"),
                "identity_accuracy": round(r.get("id_identity_accuracy", float("nan")), 3),
                "cross_view_id_accuracy": round(r.get("id_cross_view_accuracy", float("nan")), 3),
                "cross_time_id_accuracy": round(r.get("id_cross_time_accuracy", float("nan")), 3),
            }
        )
    targets = []
    for n in sorted(hull):
        cached = WORK / f"scene{n}" / "hull_target_accuracy.json"
        if not cached.is_file():
            cached.write_text(json.dumps(hull_target_accuracy(WORK / f"scene{n}")))
        targets.append({"individuals": n, **json.loads(cached.read_text())})
    target_table = (
        "\n\n## How right is the label-free count target?\n\nShare of all camera-frames "
        "where the hull target's count (`prior_presence.count_window`, `count_population`) "
        "equals the individuals visible in the ground truth, no training:\n\n"
        + markdown_table(targets)
        + "\n"
    )
    notes = Path(__file__).with_suffix(".notes.md")
    write_report(
        "count",
        "Count accuracy with an upper bound of 4 windows (synthetic scenes, 1-4 individuals)",
        rows,
        notes=(
            "For N"
            + __doc__.split("Run ``one``")[0].split("For N", 1)[1]
            + (notes.read_text() if notes.is_file() else "")
            + target_table
        ),
        extra={
            "scene_settings": SCENE,
            "train_overrides": TRAIN,
            "frames": FRAMES,
            "hull_target_accuracy": targets,
        },
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("what", choices=["one", "report", "all", "rescore"])
    p.add_argument("--n", type=int, default=2)
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--extra", nargs="*", default=[])
    p.add_argument("--presence", default="marginal", help="the prior_presence group")
    p.add_argument("--runs", nargs="*", default=[], help="rescore: only these run folders")
    a = p.parse_args()
    if a.what == "one":
        one(a.n, a.minutes, a.extra, a.presence)
    elif a.what == "all":
        for n in (1, 2, 3, 4):
            subprocess.run(
                [sys.executable, __file__, "one", "--n", str(n), "--minutes", str(a.minutes)],
                check=True,
            )
        report()
    elif a.what == "rescore":
        rescore(a.runs)
    else:
        report()


if __name__ == "__main__":
    main()
