"""What reading the footage costs before training starts, with one process and a camera each.

    .venv/bin/python tools/bench_decode.py [SCENE ...]

For each scene (default: an ``nsd-synth`` scene of 8 cameras at 1280 x 1024 as mp4 video,
300 frames, written to a temporary folder) two parts of a first run that read every camera:

* ``frame store``: decoding every frame of every camera and resizing it to the training
  size (128 x 128) into the store on disk (:class:`nsd.io.frame_store.FrameStore`, what
  ``SceneData`` builds before training); the store is deleted before each repeat;
* ``content check``: the scene check's decoding of 50 sampled frames per camera for blank,
  saturated and motionless footage (``nsd.io.scene_check._content``; a video is a seek and
  a decode per sampled frame).

Each with ``workers=1`` (this process reads the cameras one after the other: the code before
2026-12-01, the baseline row) and with a process per camera up to one per core (the
default). Seconds are medians of 3 repeats after one warm-up (the operating system's file
cache is warm in all of them). Writes ``docs/benchmarks/frame_store.{md,json}``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.core.processes import resolve_workers  # noqa: E402
from nsd.io.footage import MultiViewFootage  # noqa: E402
from nsd.io.frame_store import FrameStore  # noqa: E402
from nsd.io.scene_check import SAMPLE_FRAMES, _content  # noqa: E402
from tools.benchlib import median_time, write_report  # noqa: E402

TRAIN_SIZE = (128, 128)
SYNTH = ["image_size=[1280,1024]", "rig.count=8", "video=true", "dense=false",
         "num_frames=300"]


def _synth(root: Path) -> Path:
    out = root / "hd8_video"
    subprocess.run([str(Path(sys.executable).parent / "nsd-synth"), *SYNTH, f"out={out}"],
                   check=True, capture_output=True)
    return out


def _store_seconds(scene: Path, workers: int, cache: Path) -> float:
    def decode() -> None:
        shutil.rmtree(cache, ignore_errors=True)
        footage = MultiViewFootage(scene, image_size=TRAIN_SIZE, cache_dir=cache)
        FrameStore(footage, footage.num_frames, workers=workers)
    return median_time(decode, repeats=3, warmup=1)


def _content_seconds(scene: Path, workers: int) -> float:
    footage = MultiViewFootage(scene)
    return median_time(lambda: _content(footage, SAMPLE_FRAMES, {}, workers), repeats=3,
                       warmup=1)


def main() -> None:
    root = Path(tempfile.mkdtemp(prefix="bench-decode-"))
    scenes = [Path(a) for a in sys.argv[1:]] or [_synth(root)]
    all_cores = resolve_workers("auto", 0, "cpu")
    rows = []
    for scene in scenes:
        footage = MultiViewFootage(scene)
        w, h = footage.native_rig[0].size
        kind = "video" if footage.sources[0].path.is_file() else "image folders"
        name = f"{scene.name} ({footage.num_views} cameras, {w} x {h}, {kind}, " \
               f"{footage.num_frames} frames)"
        n = min(footage.num_views, all_cores)
        for part in ("frame store", "content check"):
            one, many = (_store_seconds(scene, k, root / "cache") if part == "frame store"
                         else _content_seconds(scene, k) for k in (1, 0))
            rows.append({"scene": name, "part": part, "seconds_one_process": round(one, 2),
                         "processes": n, "seconds": round(many, 2),
                         "speed_up": round(one / many, 2)})
            print(rows[-1], flush=True)
    shutil.rmtree(root, ignore_errors=True)
    write_report("frame_store", "Reading the footage before training: one process or a "
                 "camera each", rows, (
        "Seconds (median of 3 after a warm-up, the file cache warm) of two parts of a first "
        "run that read every camera (tools/bench_decode.py): `frame store`: every frame "
        "decoded and resized to 128 x 128 into the store on disk (`nsd.io.frame_store`); "
        "`content check`: the scene check's 50 sampled frames per camera "
        "(`nsd.io.scene_check`). `seconds_one_process`: the cameras one after the other in "
        "this process (the code before 2026-12-01, the baseline); `seconds`: a forked process "
        "per camera, at most one per core (`processes`), the default (`threads: 0`). Both "
        "write the same bytes (tests/nsd/io/test_frame_store.py). On a machine with more "
        "cores the speed-up grows to the number of cameras (the work is a camera's "
        "decoding, independent of the others), until the disk is the limit."))


if __name__ == "__main__":
    main()
