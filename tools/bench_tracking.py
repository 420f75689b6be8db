"""Tracking metrics (HOTA: TrackEval; MOTA, IDF1, ID switches: motmetrics) on three scenes.

    .venv/bin/python tools/bench_tracking.py     # ~20 minutes on 2 cores, nothing else running

For each scene, ``nsd-run`` trains for ``--steps`` (a step budget, so that the figures do
not depend on the machine's load) and exports; the rows score

* ``tracks``: the export's per-camera tracks (appearance + box IoU linking, the default);
* ``identities``: the same boxes under the final identities (one id per individual across
  cameras and time, ``identities/tracks/``);
* ``IoU-only tracks`` (baseline): the same decomposition re-exported with
  ``tracking.appearance_weight=0``: links by box overlap alone, no learned appearance.

Writes ``docs/benchmarks/tracking.{md,json}``.

    .venv/bin/python tools/bench_tracking.py --runs RUN [RUN ...] --name tracking_bound

With ``--runs`` (finished ``nsd-run`` folders, no training): each run's checkpoint is
exported twice over its scene by ``nsd-export``, with the default ``tracking.max_tracks``
(``auto``: at most the model's windows live at once) and with ``tracking.max_tracks=null``
(no bound, the baseline: a subject that links to no track opens one); the rows give the
tracks opened and, where the scene has ground truth, the metrics above.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsd.evaluation.tracking import tracking_metrics
from tools.benchlib import write_report

BIN = Path(sys.executable).parent
SCENES = {  # name -> nsd-synth overrides (None: the built-in default scene)
    "default (2 bipeds, close)": None,
    "3 bipeds, free": ["num_individuals=3", "motion.interaction=free", "seed=1"],
    "2 quadrupeds, close": ["num_individuals=2", "species=[quadruped]", "seed=2"],
}
KEYS = ("hota", "deta", "assa", "mota", "idf1", "id_switches", "recall", "precision",
        "motp_iou")


def _run(args: list[str]) -> None:
    subprocess.run([str(BIN / "nsd-run"), *args], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)


def _tracks_opened(export: Path) -> int:
    """Distinct track ids of an export (``subjects.coco.json``'s ``subject_id``)."""
    coco = json.loads((export / "subjects.coco.json").read_text())
    return len({a["subject_id"] for a in coco["annotations"]})


def bound_rows(runs: list[Path]) -> list[dict]:
    """The ``--runs`` rows: each run's checkpoint exported with and without the bound."""
    rows = []
    for run in runs:
        rec = json.loads((run / "pipeline.json").read_text())
        scene = Path(rec["scene"]["summary"]["path"])
        truth = bool(rec["scene"]["summary"].get("ground_truth"))
        with tempfile.TemporaryDirectory(prefix="bench-tracking-") as tmp:
            for label, setting in (("no bound (baseline)", "null"), ("max_tracks=auto", "auto")):
                out = Path(tmp) / setting
                subprocess.run([str(BIN / "nsd-export"), f"checkpoint={run}/train/checkpoint.pt",
                                f"scene={scene}", f"out={out}", f"tracking.max_tracks={setting}",
                                "views.tensorboard=false", "views.tsne=false", "progress=false"],
                               check=True, capture_output=True)
                m = tracking_metrics(out, scene) if truth else {}
                rows.append({"run": run.name, "scene": scene.name, "tracking": label,
                             "tracks_opened": _tracks_opened(out),
                             **{k: m.get(k, float("nan")) for k in KEYS}})
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1000, help="training steps per scene")
    ap.add_argument("--runs", type=Path, nargs="+", help="finished nsd-run folders: the bound "
                    "against no bound on each, no training")
    ap.add_argument("--name", default="tracking", help="report name under docs/benchmarks/")
    args = ap.parse_args()
    if args.runs:
        write_report(
            args.name, "Tracking: at most the model's windows live at once, against no bound",
            bound_rows(args.runs),
            notes=("Each run's checkpoint exported by `nsd-export` over all of its scene's "
                   "frames, twice: `tracking.max_tracks=auto` (the default: at most the "
                   "model's `num_windows` tracks live; a subject that links to none while that "
                   "many are live takes the most similar free one, nsd/inference/tracking.py) "
                   "and `tracking.max_tracks=null` (no bound: it opens a new track, as before). "
                   "`tracks_opened`: distinct track ids in the export. Metrics as in "
                   "`tracking.md` (ground-truth boxes of >= 16 visible pixels; NaN: a real "
                   "recording, no ground truth)."))
        return
    root = Path(tempfile.mkdtemp(prefix="bench-tracking-"))
    rows = []
    for name, synth in SCENES.items():
        scene = []
        if synth is not None:
            path = root / f"scene{len(rows)}"
            subprocess.run([str(BIN / "nsd-synth"), f"out={path}", *synth], check=True,
                           capture_output=True)
            scene = [f"scene={path}"]
        out = root / f"run{len(rows)}"
        common = [*scene, f"out={out}", f"train.trainer.max_steps={args.steps}",
                  "train.trainer.max_minutes=0", "grids.frames=0"]
        _run(common)
        rec = json.loads((out / "pipeline.json").read_text())
        tracking = rec["identities"]["summary"]["tracking"]
        ident = rec["identities"]["summary"].get("accuracy", {}).get("identity_accuracy")
        _run([*common, "+export.tracking.appearance_weight=0"])  # re-export only
        base = json.loads((out / "pipeline.json").read_text())
        for label, m in (("tracks", tracking["tracks"]), ("identities", tracking["identities"]),
                         ("IoU-only tracks (baseline)",
                          base["identities"]["summary"]["tracking"]["tracks"])):
            rows.append({"scene": name, "ids": label, **{k: m[k] for k in KEYS},
                         "camera_frames": int(m["camera_frames"]),
                         **({"identity_accuracy": ident} if label == "identities" else {})})
        print(rows[-3:], flush=True)
    write_report(
        "tracking", "Tracking: HOTA, MOTA, IDF1 and ID switches of the export", rows,
        notes=(f"`nsd-run` with `train.trainer.max_steps={args.steps}` per scene, every "
               "frame of every camera, ground-truth boxes of at least 16 visible pixels "
               "(nsd/evaluation/tracking.py): HOTA, DetA, AssA by TrackEval (means over box-IoU "
               "thresholds 0.05-0.95), MOTA, IDF1, ID switches by motmetrics (box IoU >= 0.5). "
               "`tracks`: the export's per-camera tracks; `identities`: the same boxes under "
               "the final identities across cameras; baseline: the same decomposition "
               "re-exported with `tracking.appearance_weight=0` (box overlap alone)."),
    )


if __name__ == "__main__":
    main()
