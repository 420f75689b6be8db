"""Speed against torch's CPU threads: a training step and a frame of inference, 1 .. N threads.

    .venv/bin/python tools/bench_threads.py        # ~3 minutes, nothing else running

Each row runs in a fresh process (``threads`` as a command's ``threads=`` sets them) with
its CPU affinity cut to that many cores (``taskset`` as a scheduler would), on the default
scene: the median time of a default training step (batch 16 view pairs, 128 x 128) and of
a multi-view decomposition of one frame (4 views; what nsd-eval and nsd-export do per
frame). The toolkit loads frames in the main process (no data-loader workers), so the
intra-op threads are the only ones that compete for the cores.

Writes ``docs/benchmarks/threads.{md,json}``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import write_report  # noqa: E402

CHILD = r"""
import json, sys
import numpy as np, torch
from hydra import compose, initialize_config_module
from nsd.core.threads import set_threads
from nsd.inference.multiview import InferenceSettings, decompose_views
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.training.task import NSDTask
from tools.benchlib import median_time

n = set_threads(int(sys.argv[1]))
with initialize_config_module("nsd.conf", version_base="1.3"):
    cfg = compose("train", ["data.max_frames=40"])
d = cfg.data
data = SceneData(resolve_scene(d.scene), d.image_size, d.cameras, d.val_fraction, d.max_frames)
torch.manual_seed(0)
task = NSDTask(cfg, data)
rng = np.random.default_rng(0)

def step():
    task.opt.zero_grad(set_to_none=True)
    task.training_step(10**6, rng)["loss"].backward()
    task.opt.step()

st = InferenceSettings.defaults()
grid = st.grid(data.rig, data.frame_hw)
views, bgs = data.views(30)
frame = lambda: decompose_views(task.model, views, bgs, data.num_views, st, grid)
a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
gemm = median_time(lambda: torch.mm(a, b), repeats=5, warmup=1)
print(json.dumps({"threads": n, "train_step_ms": 1000 * median_time(step, repeats=8, warmup=2),
                  "frame_ms": 1000 * median_time(frame, repeats=8, warmup=2),
                  "gemm_gflops": 2 * 2048**3 / gemm / 1e9}))
"""


def main() -> None:
    cores = len(os.sched_getaffinity(0))
    rows = []
    for n in range(1, cores + 1):
        cpus = ",".join(str(c) for c in sorted(os.sched_getaffinity(0))[:n])
        out = subprocess.run(["taskset", "-c", cpus, sys.executable, "-c", CHILD, str(n)],
                             capture_output=True, text=True, check=True, cwd=ROOT)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(rows[-1], flush=True)
    for r in rows:
        r["train_speed_up"] = rows[0]["train_step_ms"] / r["train_step_ms"]
        r["frame_speed_up"] = rows[0]["frame_ms"] / r["frame_ms"]
        r["gemm_speed_up"] = r["gemm_gflops"] / rows[0]["gemm_gflops"]
    write_report(
        "threads", "Speed against CPU threads", rows,
        notes=("Each row a fresh process with that many threads on that many cores (taskset); "
               "medians of 8 runs after 2 warm-ups; default training step (16 view pairs, "
               "128 x 128) and one frame of multi-view inference (4 views) on the default "
               "scene; gemm: a 2048 x 2048 fp32 matrix product, what more threads can give. "
               "`threads: 0` (every command's default) uses every core the process may run "
               "on; docs/scaling.md has the rule for bigger machines."),
    )


if __name__ == "__main__":
    main()
