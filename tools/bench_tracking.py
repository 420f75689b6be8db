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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1000, help="training steps per scene")
    args = ap.parse_args()
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
