"""Benchmark of ``nsd-export``: throughput at the default settings, and peak memory vs length.

A decomposition with the default model config is trained for a few steps on
the default synthetic scene (export speed does not depend on training
quality). The scene's 300 frames are then looped (symlinked PNGs, the same
calibration) into scenes of 1,000 and 10,000 frames, and each is exported with
the default settings (``conf/export.yaml``: batch of 8 instants, 64 px crops,
Parquet, projector and t-SNE of a 2,000-row sample) in a fresh subprocess, so
that every peak resident memory (``ru_maxrss``) is that export's alone.

    flock /tmp/cpu.lock .venv/bin/python tools/bench_export.py            # 1,000 and 10,000
    .venv/bin/python tools/bench_export.py --frames 200 --no-report       # a quick look

Writes ``docs/benchmarks/export.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import write_report  # noqa: E402

TRAIN_STEPS = 10


def train_checkpoint(out: Path) -> Path:
    """A default-config decomposition after a few steps on the default scene."""
    from hydra import compose, initialize_config_module

    from nsd.training.train import train

    with initialize_config_module("nsd.conf", version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"trainer.max_steps={TRAIN_STEPS}",
                "trainer.progress=false",
                "trainer.checkpoint_every=0",
                "eval_frames=2",
            ],
        )
    train(cfg, out)
    return out / "checkpoint.pt"


def looped_scene(src: Path, dst: Path, frames: int) -> Path:
    """``src``'s footage repeated to ``frames`` frames per camera (symlinks, no ground truth)."""
    from nsd.cameras.calibration_io import read_calibration

    dst.mkdir(parents=True)
    (dst / "calibration.toml").symlink_to((src / "calibration.toml").resolve())
    for cam in read_calibration(src).names:
        files = sorted((src / cam).glob("*.png"))
        (dst / cam).mkdir()
        for t in range(frames):
            (dst / cam / f"{t:06d}.png").symlink_to(files[t % len(files)].resolve())
    return dst


def child(checkpoint: str, scene: str, out: str) -> None:
    """One export with the default settings; prints its figures as JSON."""
    import torch

    import nsd.export.subjects
    from nsd.export.config import load_export_config
    from nsd.export.subjects import export_subjects

    torch.set_num_threads(2)
    streaming_peak = {}
    projector = nsd.export.subjects.write_projector

    def note_peak_then_write_projector(*args, **kwargs):  # the views start here
        streaming_peak["mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        return projector(*args, **kwargs)

    nsd.export.subjects.write_projector = note_peak_then_write_projector
    t0 = time.perf_counter()
    s = export_subjects(
        load_export_config(checkpoint=checkpoint, scene=scene, out=out, progress=False)
    )
    total = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())
    m = s.manifest
    print(
        json.dumps(
            {
                "frames": s.frames,
                "camera_frames": s.camera_frames,
                "subjects": s.subjects,
                "tracks": s.tracks,
                "stream_s": m["timing"]["seconds"],
                "frames_per_s": m["timing"]["frames_per_second"],
                "camera_frames_per_s": m["timing"]["camera_frames_per_second"],
                "views_s": m["timing"]["views_seconds"],
                "total_s": total,
                "streaming_peak_rss_mib": streaming_peak.get("mib", float("nan")),
                "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                "export_mib": size / 2**20,
            }
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--no-report", action="store_true", help="print only")
    ap.add_argument("--child", nargs=3, metavar=("CKPT", "SCENE", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    from nsd.synth import default_scene

    scene = default_scene()
    work = Path(tempfile.mkdtemp(prefix="bench_export_"))
    rows = []
    try:
        t0 = time.perf_counter()
        ckpt = train_checkpoint(work / "run")
        print(f"trained {TRAIN_STEPS} steps in {time.perf_counter() - t0:.0f} s", flush=True)
        for n in args.frames:
            loop = looped_scene(scene, work / f"loop-{n}", n)
            out = work / f"export-{n}"
            proc = subprocess.run(
                [sys.executable, __file__, "--child", str(ckpt), str(loop), str(out)],
                capture_output=True,
                text=True,
                cwd=ROOT,
                env={**os.environ, "OMP_NUM_THREADS": "2"},
            )
            if proc.returncode:
                raise SystemExit(f"export of {n} frames failed:\n{proc.stderr}")
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            print(json.dumps(r), flush=True)
            rows.append(r)
            shutil.rmtree(out)
            shutil.rmtree(loop)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.no_report:
        return
    table = [
        {
            "frames": r["frames"],
            "camera-frames": r["camera_frames"],
            "subjects": r["subjects"],
            "streaming s": round(r["stream_s"], 1),
            "frames/s": round(r["frames_per_s"], 2),
            "camera-frames/s": round(r["camera_frames_per_s"], 2),
            "projector + t-SNE s": round(r["views_s"], 1),
            "total s": round(r["total_s"], 1),
            "peak RSS, streaming MiB": round(r["streaming_peak_rss_mib"], 0),
            "peak RSS MiB": round(r["peak_rss_mib"], 0),
            "export MiB": round(r["export_mib"], 1),
        }
        for r in rows
    ]
    peaks = [r["peak_rss_mib"] for r in rows]
    notes = (
        "Default scene (4 cameras, 128 x 128, 2 people) looped to the given length; "
        f"default model config trained for {TRAIN_STEPS} steps; `nsd-export` with the "
        "default settings (batch of 8 instants, 64 px crops in compressed npz chunks, "
        "Parquet, TensorBoard projector and t-SNE of a 2,000-row sample). A frame is one "
        "instant with all 4 views. *streaming s* covers decoding, decomposition, association, "
        "tracking and writing every file; *total s* adds the projector, t-SNE, checksums and "
        "start-up (checkpoint load, median backgrounds). Each export ran in a fresh "
        "subprocess; *peak RSS* is its `ru_maxrss` over the whole export, *streaming* the "
        "same before the projector and t-SNE start. "
        f"Peak memory, 10x the frames: {peaks[-1] - peaks[0]:+.0f} MiB "
        f"({peaks[-1] / peaks[0]:.2f}x)."
        if len(peaks) > 1
        else ""
    )
    md, _ = write_report(
        "export",
        "nsd-export: throughput and peak memory",
        table,
        notes=notes,
        extra={"train_steps": TRAIN_STEPS, "runs": rows},
    )
    print(f"wrote {md}")


if __name__ == "__main__":
    main()
