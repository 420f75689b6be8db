"""Training and export memory against the recording's length: frames on disk or in memory.

    .venv/bin/python tools/bench_memory.py --frames 3000   # ~15 minutes, nothing else running

A synthetic recording of ``--frames`` frames (4 cameras, 128 x 128; the default scene's
settings otherwise) is written once; for T = 300 .. ``--frames`` frames a fresh process
builds the training data (``SceneData``, multi-view proposals as the default training
does) and runs 20 default training steps. Rows: the process's anonymous memory (RssAnon:
what cannot be dropped) and its peak resident memory (VmHWM: also file pages the OS may
drop), with the frames in the disk store (``nsd/io/frame_store.py``, the default) and,
as the baseline, held in memory (the former behaviour, forced by making the store's file
unwritable). Export rows: ``nsd-export`` of the first T frames (every camera) with a
checkpoint of 20 training steps on the same recording, in one process (``workers=1``), its
peak resident memory (``ru_maxrss`` of the export process, alone in a wrapper process).

Writes ``docs/benchmarks/memory.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import write_report  # noqa: E402

CHILD = r"""
import json, sys
import numpy as np, torch
from hydra import compose, initialize_config_module
import nsd.io.frame_store as fs
from nsd.core.threads import set_threads
from nsd.io.scene_data import SceneData
from nsd.training.task import NSDTask

scene, frames, store = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "disk"
if not store:  # the baseline: the store cannot write its file, frames stay in memory
    def refuse(*a, **k):
        raise OSError("baseline: in memory")
    fs.np.memmap = refuse
set_threads(2)  # as every command sets them (and keeps freed heap pages, as training does)
with initialize_config_module("nsd.conf", version_base="1.3"):
    cfg = compose("train", [f"data.scene={scene}", f"data.max_frames={frames}"])
d = cfg.data
data = SceneData(scene, d.image_size, d.cameras, d.val_fraction, d.max_frames)
task = NSDTask(cfg, data)
rng = np.random.default_rng(0)
for _ in range(20):
    task.opt.zero_grad(set_to_none=True)
    task.training_step(10**6, rng)["loss"].backward()
    task.opt.step()
status = dict(l.split(":", 1) for l in open("/proc/self/status").read().splitlines() if ":" in l)
mb = lambda k: int(status[k].split()[0]) / 1024
print(json.dumps({"rss_anon_mb": mb("RssAnon"), "peak_rss_mb": mb("VmHWM"),
                  "rss_file_mb": mb("RssFile")}))
"""


EXPORT = r"""
import json, resource, subprocess, sys
nsd_export, checkpoint, scene, frames, out = sys.argv[1:6]
subprocess.run([nsd_export, f"checkpoint={checkpoint}", f"scene={scene}", f"out={out}",
                f"frames={{start: 0, stop: {frames}, step: 1}}", "threads=2", "workers=1"],
               check=True, capture_output=True)
print(json.dumps({"peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2400, help="length of the long recording")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    try:
        _measure(root, args.frames)
    finally:  # the recording and its stores are ~2 GB at 3,000 frames
        shutil.rmtree(root, ignore_errors=True)


def _measure(root: Path, frames: int) -> None:
    scene = root / "long"
    subprocess.run([str(Path(sys.executable).parent / "nsd-synth"), f"out={scene}",
                    f"num_frames={frames}", "dense=false"],
                   check=True, capture_output=True)
    rows = []
    lengths = sorted({300, frames // 4, frames // 2, frames})
    for store in ("disk", "memory"):
        for T in lengths:
            out = subprocess.run([sys.executable, "-c", CHILD, str(scene), str(T), store],
                                 capture_output=True, text=True, check=True, cwd=ROOT)
            m = json.loads(out.stdout.strip().splitlines()[-1])
            frames_mb = T * 4 * 128 * 128 * 3 / 2**20
            rows.append({"frames": store, "T": T, "frame_bytes_mb": frames_mb, **m})
            print(rows[-1], flush=True)
    bin_dir = Path(sys.executable).parent
    run = root / "run"
    subprocess.run([str(bin_dir / "nsd-train"), f"data.scene={scene}", "trainer.max_steps=20",
                    "trainer.eval_at_minutes=[]", "trainer.progress=false",
                    f"hydra.run.dir={run}"], check=True, capture_output=True, cwd=ROOT)
    for T in lengths:
        out = subprocess.run([sys.executable, "-c", EXPORT, str(bin_dir / "nsd-export"),
                              str(run / "checkpoint.pt"), str(scene), str(T),
                              str(root / f"export{T}")],
                             capture_output=True, text=True, check=True, cwd=ROOT)
        m = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append({"frames": "export (disk)", "T": T,
                     "frame_bytes_mb": T * 4 * 128 * 128 * 3 / 2**20, **m})
        print(rows[-1], flush=True)
    write_report(
        "memory", "Training and export memory against the recording's length", rows,
        notes=("A fresh process per row: training data of T frames (4 cameras, 128 x 128, "
               "multi-view proposals) and 20 default training steps; `frames=disk`: the "
               "default store on disk behind a memory map, `memory`: the baseline, frames "
               "held in the process. RssAnon: anonymous memory (cannot be dropped); "
               "RssFile: file pages resident now (the OS drops them under pressure); "
               "peak_rss_mb: VmHWM, the peak of both. frame_bytes_mb: the frames' size. "
               "`export (disk)`: nsd-export of the first T frames with a 20-step checkpoint, "
               "`workers=1` (one process), its peak resident memory (ru_maxrss); with "
               "`workers: auto` every worker process has its own peak (the manifest's "
               "`timing.worker_peak_rss_mb`)."),
    )


if __name__ == "__main__":
    main()
