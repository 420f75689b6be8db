"""Speed against torch's CPU threads: training steps, whole exports and one frame of inference.

    .venv/bin/python tools/bench_threads.py        # ~9 minutes, nothing else running
    .venv/bin/python tools/bench_threads.py --spread 6   # ~6 minutes: threads_spread.md
    .venv/bin/python tools/bench_threads.py --report threads_xeon   # another machine's report

Each row runs in a fresh process (``threads`` as a command's ``threads=`` sets them) with
its CPU affinity cut to that many cores (``taskset`` as a scheduler would), on the default
scene:

* ``train_step_ms``: the median time of a default training step (``batch_size`` view pairs,
  128 x 128); ``train_step_ms_kornia_ssim`` the same with the structural loss computed by
  ``kornia.metrics.ssim`` (depthwise convolutions: the baseline before
  :mod:`nsd.ops.ssim`);
* ``train_step_ms_unfused_adam``: the same step with Adam's per-parameter loop instead of
  its fused kernel (the baseline before ``fused=True``);
* ``train_step_ms_nchw``: the same step with the convolutions' weights in torch's default
  NCHW layout instead of channels-last (the baseline before :func:`nsd.model.build.build_model`
  chose it);
* ``train_step_ms_autograd_ssim``: the same step with autograd through the SSIM's forward
  operations instead of its written-out gradient (the baseline before it);
* ``train_step_ms_heap_returned``: the same step in a process that leaves glibc's heap
  thresholds as they are (freed heap returned to the OS and faulted in again every step:
  the baseline before :func:`nsd.core.memory.keep_freed_heap`); ``train_step_ms_previous``
  the same process with all three baselines at once (the step as it was before them);
* ``train_step_ms_split``: the same step with the batch cut in two halves, each half's
  forward and backward pass in its own Python thread with one intra-op thread (on one core
  the halves one after the other), gradients accumulated (data parallelism by threads, what
  the ranks do without all_reduce);
* ``train_step_ms_one_pair``: a step of one view pair (``batch_size=1``): what a step
  costs whatever its batch (Python, dispatch, the optimiser), the part more threads cannot
  share;
* ``train_cpu_ms``: CPU time of all the process's threads in a default step (median over
  the same 60 steps), and ``train_busy_cores`` that over the step's median wall time: with
  two threads, the CPU time beyond the one-thread step's is the second core waiting
  (spinning) while the first runs what is serial, and the cost of sharing the work;
* ``train_step_ms_ranks``: the same 8 view pairs per step trained by ``n`` torchrun ranks of
  one thread each (``8 // n`` pairs per rank, gradients averaged by gloo's ``all_reduce``);
* ``export_frames_per_s``: a whole ``nsd-export`` of the 300 frames (decoding, model, files;
  median of 3), from a 20-step checkpoint, with the default ``workers: auto`` (one process
  per core decomposes batches, :mod:`nsd.core.processes`);
  ``export_frames_per_s_one_process`` the same with ``workers=1`` (every thread in one
  process: the baseline before the workers);
* ``frame_ms``: one multi-view decomposition of one frame (4 views) alone;
* ``gemm_gflops``: a 2048 x 2048 matrix product, what more threads can give.

Writes ``docs/benchmarks/threads.{md,json}``. ``--spread K`` runs only the default training
step (and the gemm) in K alternating pairs of fresh processes, 1 and every core, and writes
``docs/benchmarks/threads_spread.{md,json}``: how much one pair's speed-up says.
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

from tools.benchlib import write_report  # noqa: E402

CHILD = r"""
import dataclasses, json, sys, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import kornia, numpy as np, torch
from hydra import compose, initialize_config_module
import nsd.training.losses
from nsd.core.threads import set_threads
from nsd.export.subjects import export_subjects
from nsd.inference.multiview import InferenceSettings, decompose_views
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.training.task import NSDTask
from tools.benchlib import median_time

import nsd.core.threads
from nsd.ops import ssim as ssim_module
if sys.argv[4:] == ["heap_returned"]:
    nsd.core.threads.keep_freed_heap = lambda: False  # glibc's thresholds as they are
n, checkpoint, out = set_threads(int(sys.argv[1])), sys.argv[2], Path(sys.argv[3])
with initialize_config_module("nsd.conf", version_base="1.3"):
    cfg = compose("train", ["data.max_frames=40"])
    ecfg = compose("export", [f"checkpoint={checkpoint}", "views.tsne=false",
                              "views.tensorboard=false", "progress=false", f"threads={n}"])
d = cfg.data
data = SceneData(resolve_scene(d.scene), d.image_size, d.cameras, d.val_fraction, d.max_frames)
result = {"threads": n}

def train_ms(layout=None, conf=None, split=False, cpu_columns=False):
    torch.manual_seed(0)
    task = NSDTask(conf or cfg, data)
    if split:  # each half of the batch forward and backward in its own thread, one op thread
        pool = ThreadPoolExecutor(n, initializer=lambda: torch.set_num_threads(1))
        whole = task.losses
        def half(b):
            loss = whole(b)["loss"] / 2
            loss.backward()
            return loss.detach()
        def halves(b):
            k = b.image_v.shape[0] // 2
            cut = lambda sl: dataclasses.replace(b, **{
                f.name: getattr(b, f.name)[sl] for f in dataclasses.fields(b)
                if isinstance(getattr(b, f.name), torch.Tensor)})
            return cut(slice(0, k)), cut(slice(k, None))
        task.losses = lambda b: {"loss": sum(f.result() for f in
                                             [pool.submit(half, h) for h in halves(b)])}
    if layout is not None:
        task.model.to(memory_format=layout)
    rng = np.random.default_rng(0)
    step_no = iter(range(10**6))
    def step():
        task.opt.zero_grad(set_to_none=True)
        loss = task.training_step(next(step_no), rng)["loss"]
        if loss.requires_grad:
            loss.backward()
        task.opt.step()
    cpu = []
    def timed_step():  # and the CPU time of all the process's threads in it
        c0 = time.process_time()
        step()
        cpu.append(time.process_time() - c0)
    ms = 1000 * median_time(timed_step, repeats=60, warmup=5)
    if cpu_columns:
        result["train_cpu_ms"] = 1000 * float(np.median(cpu[5:]))
        result["train_busy_cores"] = result["train_cpu_ms"] / ms
    return ms, task

class _Traced:  # the SSIM's forward operations run outside its Function: autograd traces them
    save_for_backward = staticmethod(lambda *tensors: None)
def trace_ssim():
    ssim_module._SSIM.apply = staticmethod(lambda *a: ssim_module._SSIM.forward(_Traced, *a))

result["train_step_ms"], task = train_ms(cpu_columns=True)
a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
gemm = lambda: 2 * 2048**3 / median_time(lambda: torch.mm(a, b), repeats=5, warmup=1) / 1e9
if sys.argv[4:] == ["train_only"]:  # --spread: the default step and the gemm alone
    result["gemm_gflops"] = gemm()
    print(json.dumps(result))
    sys.exit(0)
if sys.argv[4:] == ["heap_returned"]:  # and the step as it was before all three changes
    trace_ssim()
    result["train_step_ms_previous"], _ = train_ms(torch.contiguous_format)
    print(json.dumps(result))
    sys.exit(0)
with initialize_config_module("nsd.conf", version_base="1.3"):
    one_pair = compose("train", ["data.max_frames=40", "batch_size=1"])
result["train_step_ms_one_pair"], _ = train_ms(conf=one_pair)
result["train_step_ms_split"], _ = train_ms(split=True)
fused_adam = torch.optim.Adam.__init__
def unfused(self, *args, **kwargs):
    fused_adam(self, *args, **{**kwargs, "fused": None})
torch.optim.Adam.__init__ = unfused
result["train_step_ms_unfused_adam"], _ = train_ms()
torch.optim.Adam.__init__ = fused_adam
result["train_step_ms_nchw"], _ = train_ms(torch.contiguous_format)
own = nsd.training.losses.ssim_map
nsd.training.losses.ssim_map = kornia.metrics.ssim
result["train_step_ms_kornia_ssim"], _ = train_ms()
trace_ssim()
result["train_step_ms_autograd_ssim"], _ = train_ms()
del ssim_module._SSIM.apply  # the Function's own apply again

def export_rate(workers):
    times = []
    ecfg.workers = workers
    for i in range(3):
        ecfg.out = str(out / f"export{i}")
        t0 = time.perf_counter()
        s = export_subjects(ecfg)
        times.append(time.perf_counter() - t0)
    return s.frames / sorted(times)[1]

result["export_frames_per_s"] = export_rate("auto")
result["export_frames_per_s_one_process"] = export_rate(1)

st = InferenceSettings.defaults()
grid = st.grid(data.rig, data.frame_hw)
views, bgs = data.views(30)
frame = lambda: decompose_views(task.model, views, bgs, data.num_views, st, grid)
result["frame_ms"] = 1000 * median_time(frame, repeats=24, warmup=4)
result["gemm_gflops"] = gemm()
print(json.dumps(result))
"""

RANK_CHILD = r"""
import json, sys
import numpy as np, torch
from hydra import compose, initialize_config_module
from nsd.core import distributed
from nsd.core.threads import set_threads
from nsd.io.scene_data import SceneData
from nsd.io.scenes import resolve_scene
from nsd.training.task import NSDTask
from tools.benchlib import median_time

distributed.init_from_env()
set_threads(0)  # the cores shared out among the ranks: one thread each here
world = distributed.world_size()
with initialize_config_module("nsd.conf", version_base="1.3"):
    cfg = compose("train", ["data.max_frames=40", f"batch_size={8 // world}"])
d = cfg.data
data = SceneData(resolve_scene(d.scene), d.image_size, d.cameras, d.val_fraction, d.max_frames)
torch.manual_seed(0)
task = NSDTask(cfg, data)
rng = np.random.default_rng(distributed.rank())
params = [p for g in task.opt.param_groups for p in g["params"]]
step_no = iter(range(10**6))
def step():
    task.opt.zero_grad(set_to_none=True)
    loss = task.training_step(next(step_no), rng)["loss"]
    loss.backward()
    distributed.average_gradients(params, loss.detach().reshape(1))
    task.opt.step()
ms = 1000 * median_time(step, repeats=60, warmup=5)
if distributed.rank() == 0:
    print(json.dumps(ms))
distributed.shutdown()
"""


def ranks_ms(n: int, cpus: str) -> float:
    """Median step of ``n`` torchrun ranks (one thread each) on ``cpus``, 8 // n pairs each."""
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "rank_child.py"
        script.write_text(f"import sys\nsys.path.insert(0, {str(ROOT)!r})\n{RANK_CHILD}")
        out = subprocess.run(["taskset", "-c", cpus, sys.executable, "-m",
                              "torch.distributed.run", "--standalone", f"--nproc_per_node={n}",
                              str(script)], capture_output=True, text=True, check=True, cwd=ROOT)
    return float(out.stdout.strip().splitlines()[-1])


SPEED = {  # column -> True when larger is faster
    "train_step_ms": False, "train_step_ms_unfused_adam": False, "train_step_ms_ranks": False,
    "train_step_ms_kornia_ssim": False, "train_step_ms_autograd_ssim": False,
    "train_step_ms_heap_returned": False, "train_step_ms_nchw": False,
    "train_step_ms_previous": False, "train_step_ms_split": False,
    "train_step_ms_one_pair": False,
    "export_frames_per_s": True,
"export_frames_per_s_one_process": True, "frame_ms": False, "gemm_gflops": True,
}


def child(threads: int, cpus: str, checkpoint: str, tmp: str, *mode: str) -> dict:
    """The figures of one fresh ``CHILD`` process with ``threads`` torch threads on ``cpus``
    (``mode``: ``heap_returned`` or ``train_only``; none: every figure)."""
    out = subprocess.run(["taskset", "-c", cpus, sys.executable, "-c", CHILD, str(threads),
                          checkpoint, tmp, *mode],
                         capture_output=True, text=True, check=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def spread(pairs: int, report: str = "threads_spread") -> None:
    """``pairs`` alternating fresh processes of 1 and of every core, the default training step
    and the gemm only: how far one pair's speed-up is from another's. Writes
    ``<report>.{md,json}`` (default ``threads_spread``)."""
    cores = sorted(os.sched_getaffinity(0))
    n = len(cores)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(pairs):
            row = {"pair": i + 1}
            for threads in ((1, n) if i % 2 == 0 else (n, 1)):  # which goes first alternates
                got = child(threads, ",".join(str(c) for c in cores[:threads]), "-", tmp,
                            "train_only")
                row[f"train_step_ms_{threads}"] = got["train_step_ms"]
                row[f"gemm_gflops_{threads}"] = got["gemm_gflops"]
            row["train_speed_up"] = row["train_step_ms_1"] / row[f"train_step_ms_{n}"]
            row["gemm_speed_up"] = row[f"gemm_gflops_{n}"] / row["gemm_gflops_1"]
            rows.append(row)
            print(row, flush=True)
    summary = {}
    for key in ("train_step_ms_1", f"train_step_ms_{n}", "train_speed_up", "gemm_speed_up"):
        values = [r[key] for r in rows]
        summary |= {f"{key}_median": float(np.median(values)), f"{key}_min": min(values),
                    f"{key}_max": max(values)}
    pooled = float(np.median([r["train_step_ms_1"] for r in rows])
                   / np.median([r[f"train_step_ms_{n}"] for r in rows]))
    write_report(
        report, f"Training on 1 and {n} threads: the spread between processes", rows,
        extra={**summary, "train_speed_up_of_medians": pooled, "pairs": pairs},
        notes=(f"`tools/bench_threads.py --spread {pairs}`: {pairs} pairs of fresh processes, "
               f"one on 1 core and one on {n} (taskset, that many torch threads), which of "
               "the two goes first alternating from pair to pair; in each, the median of 60 "
               "default training steps after 5 warm-ups from a fresh model (default scene, "
               "batch and size, as `train_step_ms` of threads.md) and a 2048 x 2048 fp32 "
               "matrix product (median of 5), what more threads can give. `train_speed_up`: "
               "the pair's 1-core step over its n-core step; `train_speed_up_of_medians`: the "
               "median 1-core step over the median n-core step."),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spread", type=int, default=0, metavar="K",
                    help="only K alternating pairs of 1- and n-core processes of the default "
                         "training step (threads_spread.md)")
    ap.add_argument("--report", default=None,
                    help="the report's name under docs/benchmarks/ (default: threads, or "
                         "threads_spread with --spread), e.g. to keep another machine's")
    args = ap.parse_args()
    if args.spread:
        spread(args.spread, args.report or "threads_spread")
        return
    cores = sorted(os.sched_getaffinity(0))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        subprocess.run([str(Path(sys.executable).parent / "nsd-train"), "trainer.max_steps=20",
                        f"hydra.run.dir={run}"], check=True, capture_output=True, cwd=ROOT)
        for n in range(1, len(cores) + 1):
            cpus = ",".join(str(c) for c in cores[:n])
            rows.append(child(n, cpus, str(run / "checkpoint.pt"), tmp))
            before = child(n, cpus, str(run / "checkpoint.pt"), tmp, "heap_returned")
            rows[-1]["train_step_ms_heap_returned"] = before["train_step_ms"]
            rows[-1]["train_step_ms_previous"] = before["train_step_ms_previous"]
            rows[-1]["train_step_ms_ranks"] = (rows[-1]["train_step_ms"] if n == 1
                                               else ranks_ms(n, cpus))
            print(rows[-1], flush=True)
    first = rows[0]
    for r in rows:
        for k, larger in SPEED.items():
            r[f"{k}_speed_up"] = r[k] / first[k] if larger else first[k] / r[k]
    last = rows[-1]
    write_report(
        args.report or "threads", "Speed against CPU threads", rows,
        extra={
            "train_ssim_gain_1_thread": first["train_step_ms_kornia_ssim"] / first["train_step_ms"],
            "train_fused_adam_gain_1_thread": (first["train_step_ms_unfused_adam"]
                                               / first["train_step_ms"]),
            "train_written_ssim_gradient_gain_1_thread": (first["train_step_ms_autograd_ssim"]
                                                          / first["train_step_ms"]),
            "train_channels_last_gain_1_thread": (first["train_step_ms_nchw"]
                                                  / first["train_step_ms"]),
            "train_channels_last_gain_2_threads": (last["train_step_ms_nchw"]
                                                   / last["train_step_ms"]),
            "train_kept_heap_gain_1_thread": (first["train_step_ms_heap_returned"]
                                              / first["train_step_ms"]),
            "train_kept_heap_gain_2_threads": (last["train_step_ms_heap_returned"]
                                               / last["train_step_ms"]),
            "train_gain_vs_previous_1_thread": (first["train_step_ms_previous"]
                                                / first["train_step_ms"]),
            "train_gain_vs_previous_2_threads": (last["train_step_ms_previous"]
                                                 / last["train_step_ms"]),
            "train_speed_up_vs_before": first["train_step_ms_kornia_ssim"] / last["train_step_ms"],
        },
        notes=("Each row a fresh process with that many threads on that many cores (taskset), "
               "on the default scene. Training: medians of 60 steps after 5 warm-ups from a "
               "fresh model (default batch, 128 x 128); `unfused_adam`: Adam's per-parameter loop "
               "instead of its fused kernel (the baseline); `ranks`: the same 8 view pairs "
               "per step over n torchrun ranks of one thread each (8 // n pairs per rank, "
               "gradients averaged by all_reduce), rank 0's median of 60 steps; `split`: the "
               "batch's two halves forward and backward in two Python threads of one intra-op "
               "thread each (one after the other on one core), gradients accumulated; "
               "`one_pair`: a step of one view pair (`batch_size=1`), the part of a step "
               "that does not grow with the batch; `train_cpu_ms`: CPU time of all threads "
               "per default step (median of the same 60), `train_busy_cores` that over its "
               "median wall time; "
               "`nchw`: the convolutions' weights in the NCHW layout instead of "
               "channels-last (the baseline); `autograd_ssim`: autograd through the SSIM's "
               "forward operations instead of "
               "its written-out gradient (the baseline); `heap_returned`: a process with "
               "glibc's heap thresholds as they are, freed heap given back and faulted in "
               "again every step (the baseline before keep_freed_heap); `previous`: the "
               "same process with all three baselines at once (NCHW, autograd SSIM, heap "
               "returned: the step as it was before they changed); "
               "`kornia_ssim`: the structural loss by "
               "kornia's depthwise convolutions instead of nsd/ops/ssim.py's matrix products "
               "(the baseline). Export: a whole `nsd-export` of the 300 frames from a 20-step "
               "checkpoint, median of 3, with `workers: auto` (one decomposing process per "
               "core) and, as the baseline, `workers=1` (one process, every thread). "
               "`frame_ms`: one multi-view decomposition of one "
               "frame alone. gemm: a 2048 x 2048 fp32 matrix product, what more threads can "
               "give. train_speed_up_vs_before: the last row's new code against the first "
               "row's baseline. `threads: 0` (every command's default) uses every core the "
               "process may run on; docs/scaling.md has the rule for bigger machines."),
    )


if __name__ == "__main__":
    main()
