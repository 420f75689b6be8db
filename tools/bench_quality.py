"""Does the label-free quality report tell a good run from a bad one? Its figures beside the
ground-truth metrics of the same runs.

    .venv/bin/python tools/bench_quality.py          # ~12 minutes on 2 cores, nothing else running

Each case is one ``nsd-run`` (a step budget, so that the figures do not depend on the
machine's load) on a synthetic scene with ground truth; the ``quality`` stage
(:mod:`nsd.evaluation.quality`) sees only the footage, the calibration and the export. Cases
that should look bad: a short training, a calibration with one camera turned by 2 degrees,
three people in a huddle, a subject that lingers under the plain temporal median background.
Ground truth per row: detection rate and visible-mask mIoU of the evaluate stage (held-out
frames), and identity accuracy of the identities stage (every exported row).

Writes ``docs/benchmarks/quality.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsd.io.scenes import resolve_scene
from tools.benchlib import write_report

BIN = Path(sys.executable).parent
TURN = np.radians(2.0)  # pan of the turned camera
CASES = [  # name, nsd-synth overrides (None: the default scene), nsd-run overrides, turn cam2
    ("default scene, 1000 steps", None, ["train.trainer.max_steps=1000"], False),
    ("default scene, 300 steps", None, ["train.trainer.max_steps=300"], False),
    ("default scene, cam2 turned 2 degrees", None, ["train.trainer.max_steps=1000"], True),
    ("3 bipeds in a huddle", ["num_individuals=3", "motion.interaction=huddle", "seed=1"],
     ["train.trainer.max_steps=1000", "train.model.num_windows=3"], False),
    ("lingering subject, median background", ["motion.linger=0.7", "seed=3"],
     ["train.trainer.max_steps=1000", "train.data.background=median"], False),
]
QUALITY = ("explained", "spill", "consistency", "identity_switches", "view_agreement",
           "count_changes")
TRUTH = {"detection_rate": "detection", "mask_miou": "mask_miou",
         "association_accuracy": "association"}


def _vector(tail: str, key: str) -> tuple[re.Match, np.ndarray]:
    m = re.search(rf"{key} = \[([^\]]*)\]", tail)
    return m, np.array([float(x) for x in m.group(1).split(",") if x.strip()])


def _turn(scene: Path, camera_section: str = "cam_2") -> None:
    """Pan one camera of calibration.toml by TURN radians about its own vertical axis (centre
    kept): the calibration then says it looks TURN to the side of where the footage was taken."""
    path = scene / "calibration.toml"
    head, tail = path.read_text().split(f"[{camera_section}]", 1)
    c, s = np.cos(TURN), np.sin(TURN)
    pan = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about the camera's y axis
    for key in ("rotation", "translation"):  # x_cam = R X + t becomes pan (R X + t)
        m, vec = _vector(tail, key)
        new = (cv2.Rodrigues(pan @ cv2.Rodrigues(vec)[0])[0].ravel() if key == "rotation"
               else pan @ vec)
        tail = f"{tail[: m.start(1)]}{', '.join(repr(float(x)) for x in new)}{tail[m.end(1):]}"
    path.write_text(f"{head}[{camera_section}]{tail}")


def _scene(root: Path, i: int, synth: list[str] | None, turn: bool) -> Path:
    scene = root / f"scene{i}"
    if (scene / "calibration.toml").is_file():  # kept from an earlier run (--keep)
        return scene
    if synth is None:
        shutil.copytree(resolve_scene(None), scene, ignore=shutil.ignore_patterns(".cache"))
    else:
        subprocess.run([str(BIN / "nsd-synth"), f"out={scene}", *synth], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if turn:
        _turn(scene)
    return scene


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the scenes and runs in this folder (a second call resumes them)")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-quality-") as tmp:
        root = args.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        for i, (name, synth, run, turn) in enumerate(CASES):
            scene = _scene(root, i, synth, turn)
            out = root / f"run{i}"
            subprocess.run(
                [str(BIN / "nsd-run"), f"scene={scene}", f"out={out}", *run,
                 "train.trainer.max_minutes=0", "train.trainer.progress=false", "grids.frames=0",
                 "overlays.enabled=false", "formats.enabled=false", "netepu.geometry=null",
                 "netepu.texture=null", "+export.views.tensorboard=false",
                 "+export.views.tsne=false", "+export.progress=false"],
                check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            record = json.loads((out / "pipeline.json").read_text())
            ev = record["evaluate"]["summary"]["metrics"]
            ident = record["identities"]["summary"].get("accuracy", {})
            q = record["quality"]["summary"]
            row = {"case": name}
            row |= {short: ev.get(key) for key, short in TRUTH.items()}
            row["identity_accuracy"] = ident.get("identity_accuracy")
            row |= {f"q_{k}": q["summary"].get(k) for k in QUALITY}
            row["warnings"] = len(q["warnings"])
            row["warned_about"] = "; ".join(w.split(":")[0][:60] for w in q["warnings"])
            rows.append(row)
            print(row, flush=True)
    notes = (
        "Left (ground truth): detection rate (visible-mask IoU >= 0.5) and visible-mask mIoU "
        "of the evaluate stage on 30 held-out frames, association accuracy, identity accuracy "
        "of every exported row (identities from NSD's appearance vectors: no NeTePu model in "
        "these runs). Right (`q_`, label-free, `<out>/quality/quality.json`, 100 frames): "
        "share of the moving foreground inside some mask (`explained`), share of mask pixels "
        "on background (`spill`), share of mask pixels confirmed by the other cameras' hull "
        "(`consistency`), identity changes per track step, cameras agreeing on a subject's "
        "identity, frames whose subject count changes. `warnings`: how many of the report's "
        "limits (`nsd.evaluation.quality.TRUST_LIMITS`) the run crossed. One seed per case; "
        "`tools/bench_quality.py`."
    )
    write_report("quality", "Label-free quality report against ground truth", rows, notes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
