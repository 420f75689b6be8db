"""Backgrounds when a subject lingers: the temporal median, the two-colour estimate, a plate.

    .venv/bin/python tools/bench_background.py

Synthetic scenes (``nsd-synth``, 4 cameras, 300 frames at 128 x 128) in which the first
individual stays where it is for the first ``motion.linger`` share of the recording, then
walks like the others, and the default scene (nobody lingers). For each background
(``data.background=median``, ``data.background=modes`` of ``nsd/cues/background.py``, and
each camera's true empty backdrop given as a plate, the upper bound) it reports:

* ``bg_wrong``: share of background pixels more than 24 grey levels from the true
  backdrop (the scene's ``gt/background``), mean over cameras;
* ``uncertain``: share reported as having two stable colours, mean over cameras;
  ``stayed``: the share of it where something stayed for a stretch of the recording and
  the estimate replaced it or kept a subject-like colour (``BackgroundEstimate.stayed``),
  mean over cameras, and
  ``warned``: the cameras the scene check warns about (``nsd.io.scene_check.lingered``:
  with ``modes``, ``stayed`` above 0.5 %; with ``median``, ``uncertain`` above 0.5 %), and
  ``warned_before``: those it warned about until 2026-12-01 (``uncertain`` above 0.5 %);
* the hull-only decomposition's visible-mask detection rate (IoU >= 0.5) and mIoU
  (``nsd.evaluation.hull_baseline``, every 3rd frame), while the subject lingers, after,
  and over all frames;
* for each lingering scene its twin: the same scene with ``motion.linger=0.0`` (nobody
  lingers), split at the same frame, the comparison the issue's target is stated against.

Writes ``docs/benchmarks/background.{md,json}``.

    .venv/bin/python tools/bench_background.py --cost [SCENE ...]

The estimate's cost alone: seconds (median of 3) of camera 0's estimate from 50 frames, by
method, of the linger 0.7 scene upscaled to 512 x 512 and 1280 x 1024 and of each SCENE at
its own size, for this commit's densest colour and for the one before 2026-12-01
(:func:`_densest_before`, the baseline row). Writes ``docs/benchmarks/background_cost.{md,json}``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.cues import background  # noqa: E402
from nsd.evaluation.hull_baseline import evaluate_hull  # noqa: E402
from nsd.inference.multiview import InferenceSettings  # noqa: E402
from nsd.io.footage import MultiViewFootage  # noqa: E402
from nsd.io.ground_truth import GroundTruth  # noqa: E402
from nsd.io.scene_check import LINGER_SHARE, lingered  # noqa: E402
from nsd.io.scene_data import SceneData  # noqa: E402
from nsd.io.scenes import resolve_scene  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

SCENES = [  # name, nsd-synth overrides (None: the built-in default scene), linger share
    ("default (no lingering)", None, 0.0),
    ("linger 0.7, seed 3", ["motion.linger=0.7", "seed=3"], 0.7),
    ("linger 0.85, seed 5", ["motion.linger=0.85", "seed=5"], 0.85),
    ("linger 0.6, 3 individuals, seed 7", ["motion.linger=0.6", "seed=7",
                                            "num_individuals=3"], 0.6),
    # added after the subject-likeness rule was chosen on the three above, to check it
    ("linger 0.7, seed 11", ["motion.linger=0.7", "seed=11"], 0.7),
    ("linger 0.8, seed 13", ["motion.linger=0.8", "seed=13"], 0.8),
    ("linger 0.75, 3 individuals, seed 17", ["motion.linger=0.75", "seed=17",
                                             "num_individuals=3"], 0.75),
]
STEP = 3


def _synth(root: Path, overrides: list[str]) -> Path:
    out = root / "_".join(o.replace("=", "") for o in overrides)
    subprocess.run([str(Path(sys.executable).parent / "nsd-synth"), *overrides, f"out={out}"],
                   check=True, capture_output=True)
    return out


def _with_plates(scene: Path, root: Path) -> Path:
    """A copy of ``scene`` (links) whose background/ holds each camera's true backdrop."""
    out = root / (scene.name + "-plates")
    out.mkdir()
    for p in scene.iterdir():
        if p.name not in (".cache", "background"):
            (out / p.name).symlink_to(p.resolve())
    shutil.copytree(scene / "gt" / "background", out / "background")
    return out


def _bg_wrong(data: SceneData, scene: Path) -> float:
    H, W = data.frame_hw
    shares = []
    for v, cam in enumerate(data.rig.names):
        true = cv2.cvtColor(cv2.imread(str(scene / "gt" / "background" / f"{cam}.png")),
                            cv2.COLOR_BGR2RGB)
        true = cv2.resize(true, (W, H), interpolation=cv2.INTER_AREA).astype(int)
        est = (data.backgrounds[v].permute(1, 2, 0).numpy() * 255).round().astype(int)
        shares.append(float((np.abs(est - true).max(-1) > 24).mean()))
    return float(np.mean(shares))


def _cost(scene: Path) -> dict[str, float]:
    """Seconds of one camera's estimate (camera 0 of ``scene``, 50 frames) by method and
    frame size, the frames upscaled for the larger sizes (median of 3 runs)."""
    from nsd.cues.background import estimate_background

    src = MultiViewFootage(scene).sources[0]
    idx = np.unique(np.linspace(0, src.num_frames - 1, 50).round().astype(int))
    stack = np.stack([src.read(int(t)) for t in idx])
    out = {}
    for w, h in ((128, 128), (512, 512), (1280, 1024)):
        big = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_NEAREST) for f in stack])
        for method in ("median", "modes"):
            runs = []
            for _ in range(3):
                t0 = time.perf_counter()
                estimate_background(big, method)
                runs.append(time.perf_counter() - t0)
            out[f"{method}_{w}x{h}"] = round(float(np.median(runs)), 3)
    return out


def _densest_before(samples: np.ndarray, allowed: np.ndarray):
    """The densest colour as it was computed until 2026-12-01 (the same result): the largest
    absolute difference over the channels of an (N, N, K, 3) table, a NaN median."""
    close = np.abs(samples[:, None] - samples[None]).max(-1) <= background.MODE_TOLERANCE
    close &= allowed[:, None] & allowed[None]
    best = close.sum(1).argmax(0)
    members = close[best, :, np.arange(samples.shape[1])].T
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        colour = np.nanmedian(np.where(members[..., None], samples, np.nan), axis=0)
    return colour, members.sum(0), members


def _seconds(stack: np.ndarray, method: str) -> float:
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        background.estimate_background(stack, method)
        runs.append(time.perf_counter() - t0)
    return round(float(np.median(runs)), 3)


def cost(scenes: list[Path]) -> None:
    """``--cost``: the estimate's seconds, this commit's densest colour against the one
    before (module docstring)."""
    root = Path(tempfile.mkdtemp(prefix="bench-background-cost-"))
    lingering = _synth(root, ["motion.linger=0.7", "seed=3"])
    cases = []
    for scene in [lingering, *scenes]:
        src = MultiViewFootage(scene).sources[0]
        idx = np.unique(np.linspace(0, src.num_frames - 1, 50).round().astype(int))
        stack = np.stack([src.read(int(t)) for t in idx])
        if scene == lingering:
            for w, h in ((512, 512), (1280, 1024)):
                cases.append((f"linger 0.7, seed 3, upscaled to {w} x {h}", np.stack(
                    [cv2.resize(f, (w, h), interpolation=cv2.INTER_NEAREST) for f in stack])))
        else:
            cases.append((f"{scene.name} ({stack.shape[2]} x {stack.shape[1]})", stack))
    now = background._densest
    rows = []
    for name, stack in cases:
        for method in ("median", "modes"):
            row = {"scene": name, "method": method}
            for label, fn in (("before", _densest_before), ("this commit", now)):
                background._densest = fn
                row[f"seconds_{label.replace(' ', '_')}"] = _seconds(stack, method)
            background._densest = now
            row["speed_up"] = round(row["seconds_before"] / row["seconds_this_commit"], 2)
            rows.append(row)
            print(row, flush=True)
    write_report("background_cost", "What a camera's background estimate costs", rows, (
        "Seconds (median of 3 runs, one process alone) of camera 0's estimate from 50 frames "
        "spread over the recording (`nsd.cues.background.estimate_background`; frames above "
        "512 x 512 are analysed at that size), by method; `before`: the densest colour as "
        "computed until 2026-12-01 (`tools/bench_background.py`'s `_densest_before`, the same "
        "output), `this commit`: a channel at a time into reused buffers, the median by "
        "sorting. `median` finds its uncertain pixels (two stable colours) the same way, so "
        "both methods pay for it. The cost grows with the share "
        "of pixels whose median colour is off in at least 15 % of the frames (those are "
        "analysed), which lingering subjects raise. Rows named by a folder: a scene given on "
        "the command line."))


def main() -> None:
    if "--cost" in sys.argv[1:]:
        cost([Path(a) for a in sys.argv[1:] if a != "--cost"])
        return
    root = Path(tempfile.mkdtemp(prefix="bench-background-"))
    rows, scenes = [], {}
    runs = []
    for name, overrides, linger in SCENES:
        runs.append((name, overrides, linger, linger, ("median", "modes", "plate")))
        if linger > 0:  # its twin: the same scene (seed, rig, textures) without lingering
            twin = [o for o in overrides if not o.startswith("motion.linger=")]
            runs.append((f"{name}: twin, nobody lingers", [*twin, "motion.linger=0.0"], 0.0,
                         linger, ("modes",)))
    for name, overrides, linger, split_at, methods in runs:
        scene = resolve_scene(None) if overrides is None else _synth(root, overrides)
        scenes.setdefault(linger, scene)
        gt = GroundTruth.load(scene)
        k = len(json.loads((scene / "gt" / "scene.json").read_text())["individuals"])
        for method in methods:
            where = _with_plates(scene, root) if method == "plate" else scene
            data = SceneData(where, (128, 128), val_fraction=0.0,
                             background="median" if method == "plate" else method)
            fp = data.footage
            est = [fp.background_estimate(v) for v in range(fp.num_views)]
            uncertain = float(np.mean([e.uncertain_share for e in est]))
            grid = InferenceSettings.defaults().grid(data.rig, data.frame_hw)
            T = len(data.frames)
            split = round(split_at * T)  # a twin is split where its lingering scene is
            parts = {"lingering": range(0, split, STEP), "after": range(split, T, STEP),
                     "all": range(0, T, STEP)}
            row = {"scene": name, "background": method,
                   "bg_wrong": round(_bg_wrong(data, scene), 4),
                   "uncertain": round(uncertain, 4)}
            if method != "plate":  # a plate is the background: nothing uncertain, no warning
                row |= {"stayed": round(float(np.mean([e.stayed_share for e in est])), 4),
                        "warned": sum(lingered(e, method) for e in est),
                        "warned_before": sum(e.uncertain_share > LINGER_SHARE for e in est)}
            for part, frames in parts.items():
                if not len(frames):
                    continue
                m = evaluate_hull(data, list(frames), gt, grid, k)
                row[f"detection_{part}"] = round(m["detection_rate"], 3)
                row[f"miou_{part}"] = round(m["mask_miou"], 3)
            rows.append(row)
            print(row, flush=True)
    notes = (
        "`bg_wrong`: share of background pixels more than 24 grey levels from the true "
        "backdrop (mean over the 4 cameras). `uncertain`: share with two stable colours; "
        "`stayed`: the share of it where something stayed for a stretch and the estimate "
        "replaced it or kept a subject-like colour, both means over the cameras; `warned`: "
        "the cameras the scene check warns about (with `modes` those whose `stayed` exceeds "
        "0.5 %, with `median` those whose `uncertain` does); `warned_before`: those it "
        "warned about until 2026-12-01 "
        "(`uncertain` above 0.5 %, either method). Detection and mIoU: the hull-only "
        "decomposition (no learning; every 3rd frame), split into the frames while the "
        "first individual lingers and after it left, and over all frames (`_all`). "
        "`plate`: each camera's true empty backdrop given as "
        "`scene/background/<camera>.png`, the upper bound. `twin`: the "
        "same scene (seed, cameras, textures) with `motion.linger=0.0`, split at the same "
        "frame, the comparison the lingering scene's figures should come within 0.05 of. Cost: "
        "`estimate_seconds` (median of 3) of one camera's estimate from 50 frames of the "
        "linger 0.7 scene, upscaled to each size (frames above 512 x 512 are analysed at "
        "that size), by method."
    )
    write_report("background", "Backgrounds when a subject lingers", rows, notes,
                 extra={f"estimate_seconds_{k}": v for k, v in _cost(scenes[0.7]).items()})


if __name__ == "__main__":
    main()
