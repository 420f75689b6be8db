"""The bad-input table: broken scenes, configs and files given to every command, as a user would.

Each case runs one command in a fresh subprocess and is scored by what the user sees:

* ``clean error``: exit status 2, no Python traceback, a message naming the culprit
  (the key, file, camera or frame given by the case), nothing left under a final name;
* ``warning``: the run finishes (exit 0) and a warning names the culprit and says what to do;
* ``silent``: exit 0 without the expected warning (silent nonsense);
* ``crash``: any other exit status, a signal or a traceback.

Usage::

    python tools/bad_input.py            # writes docs/benchmarks/bad_input.{md,json}
    python tools/bad_input.py --only lr  # the cases whose name contains "lr" (no report)
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.benchlib import write_report

BIN = Path(sys.executable).parent
FAST = [
    "train.trainer.max_steps=2", "train.trainer.max_minutes=0", "train.data.image_size=[64,64]",
    "train.eval_frames=2", "grids.frames=1",
]


@dataclass
class Case:
    """One bad input: ``args`` for ``command``; ``setup(work)`` builds files and may return
    extra arguments; ``culprit`` must appear in the message; ``expect`` is error or warning."""

    name: str
    command: str
    args: list[str]
    culprit: str
    expect: str = "error"
    setup: Callable[[Path], list[str]] | None = None
    fast: bool = True
    extra_env: dict[str, str] = field(default_factory=dict)


# ------------------------------------------------------------------ scene surgery
def _scene(work: Path, base: Path) -> Path:
    dst = work / "scene"
    shutil.copytree(base, dst)
    return dst


def _frames(scene: Path, cam: str) -> list[Path]:
    return sorted((scene / cam).glob("*.png"))


def _edit(base: Path, fn: Callable[[Path], None]) -> Callable[[Path], list[str]]:
    def setup(work: Path) -> list[str]:
        s = _scene(work, base)
        fn(s)
        return [f"scene={s}"]
    return setup


def _resize_one(s: Path) -> None:
    f = _frames(s, "cam1")[3]
    cv2.imwrite(str(f), cv2.resize(cv2.imread(str(f)), (48, 40)))


def _drop_frame(s: Path) -> None:
    """cam2 dropped frame 7 and numbered on: as many files, names shifted."""
    fs = _frames(s, "cam2")
    for f in reversed(fs[7:]):
        f.rename(f.with_name(f"{int(f.stem) + 1:06d}.png"))


def _blank(value: int) -> Callable[[Path], None]:
    def fn(s: Path) -> None:
        f = _frames(s, "cam0")[5]
        cv2.imwrite(str(f), np.full_like(cv2.imread(str(f)), value))
    return fn


def _one_short(s: Path) -> None:
    _frames(s, "cam1")[-1].unlink()


def _bad_plate(s: Path) -> None:
    (s / "background").mkdir()
    cv2.imwrite(str(s / "background" / "cam0.png"), np.zeros((10, 10, 3), np.uint8))


def _still(s: Path) -> None:
    for cam in ("cam0", "cam1", "cam2", "cam3"):
        fs = _frames(s, cam)
        for f in fs[1:]:
            shutil.copy(fs[0], f)


def _corrupt(s: Path) -> None:
    _frames(s, "cam3")[4].write_bytes(b"not a png")


def _toml_value(v: object) -> str:
    if isinstance(v, float) and v != v:
        return "nan"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(v)


def _calib(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    """Edit the scene's calibration.toml as data (``fn`` changes the parsed tables)."""
    def edit(s: Path) -> None:
        p = s / "calibration.toml"
        data = tomllib.loads(p.read_text())
        fn(data)
        lines = []
        for key, cam in data.items():
            lines += [f"[{key}]", *(f"{k} = {_toml_value(v)}" for k, v in cam.items()), ""]
        p.write_text("\n".join(lines))
    return edit


def _scaled(factor: float):
    def edit(data: dict) -> None:
        for cam in data.values():
            if "translation" in cam:
                cam["translation"] = [factor * v for v in cam["translation"]]
    return edit


def _singular(data: dict) -> None:
    data["cam_0"]["matrix"][0] = [0.0, 0.0, 32.0]


def _nan_calib(data: dict) -> None:
    data["cam_0"]["translation"][0] = float("nan")


def _drop_camera_calib(data: dict) -> None:
    del data["cam_3"]


def _one_camera(s: Path) -> None:
    for cam in ("cam1", "cam2", "cam3"):
        shutil.rmtree(s / cam)
    _calib(lambda d: [d.pop(k) for k in ("cam_1", "cam_2", "cam_3")])(s)


def _empty(work: Path) -> list[str]:
    (work / "empty").mkdir()
    return [f"scene={work / 'empty'}"]


# ------------------------------------------------------------------ files
def _file(name: str, write: Callable[[Path], None], key: str = "checkpoint"):
    def setup(work: Path) -> list[str]:
        p = work / name
        write(p)
        return [f"{key}={p}"]
    return setup


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch /tmp/bad_input_pwned",))


def _pickle_payload(p: Path) -> None:
    with open(p, "wb") as f:
        pickle.dump({"format": "x", "payload": _Evil()}, f)


_OWNERS: list[subprocess.Popen] = []


def _busy(work: Path) -> list[str]:
    """Another live run holds ``work/run`` (a process holding its lock)."""
    code = ("import sys\nfrom nsd.core.run_folder import RunFolder\n"
            f"with RunFolder({str(work / 'run')!r}, 'nsd-run', log=False):\n"
            "    print('held', flush=True)\n    sys.stdin.readline()\n")
    owner = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    assert owner.stdout.readline().strip() == "held"
    _OWNERS.append(owner)
    return [f"out={work / 'run'}"]


def _out_is_file(work: Path) -> list[str]:
    (work / "taken").write_text("a file")
    return [f"out={work / 'taken'}"]


def _cases(base: Path, nodense: Path) -> list[Case]:
    run, sc = "nsd-run", [f"scene={base}"]
    c = [
        # ---- config values
        Case("lr nan", run, [*sc, "train.optim.lr_detector=nan"], "lr_detector"),
        Case("max_steps abc", run, [*sc, "train.trainer.max_steps=abc"], "max_steps"),
        Case("batch_size -1", run, [*sc, "train.batch_size=-1"], "batch_size"),
        Case("batch_size 0", run, [*sc, "train.batch_size=0"], "batch_size"),
        Case("negative prior weight", run, [*sc, "train.prior_position.weight=-1"],
             "prior_position.weight"),
        Case("image_size 0x0", run, [*sc, "train.data.image_size=[0,0]"], "image_size"),
        Case("val_fraction 1.5", run, [*sc, "train.data.val_fraction=1.5"], "val_fraction"),
        Case("num_windows 0", run, [*sc, "train.model.num_windows=0"], "num_windows"),
        Case("crop_size 0", run, [*sc, "train.model.crop_size=0"], "crop_size"),
        Case("ssim_weight inf", run, [*sc, "train.loss.ssim_weight=inf"], "ssim_weight"),
        Case("model.mode unknown", run, [*sc, "train.model.mode=foo"], "mode"),
        Case("threads -1", run, [*sc, "threads=-1"], "threads"),
        Case("device unknown", run, [*sc, "device=gpu"], "device"),
        Case("device=cuda without a CUDA GPU", run, [*sc, "device=cuda"], "device"),
        Case("data.background unknown", run, [*sc, "train.data.background=mean"],
             "background"),
        Case("grids.frames -1", run, [*sc, "grids.frames=-1"], "grids.frames"),
        Case("identities.method unknown", run, [*sc, "netepu.identities.method=foo"], "method"),
        Case("identities.jump 0", run, [*sc, "netepu.identities.jump=0"], "jump"),
        Case("inference.hole_share 2", run, [*sc, "train.inference.hole_share=2"],
             "hole_share"),
        Case("inference.island_share -1", run, [*sc, "train.inference.island_share=-1"],
             "island_share"),
        Case("inference.neighbour_sigma 0", run, [*sc, "train.inference.neighbour_sigma=0"],
             "neighbour_sigma"),
        Case("inference.colour_model_separation high", run,
             [*sc, "train.inference.colour_model_separation=high"], "colour_model_separation"),
        Case("netepu.species unknown", run, [*sc, "netepu.species=cow"], "species"),
        Case("quality.max_frames -1", run, [*sc, "quality.max_frames=-1"], "max_frames"),
        Case("unknown key", run, [*sc, "train.nonsense=1"], "nonsense"),
        Case("export batch_size 0", run, [*sc, "+export.batch_size=0"], "batch_size"),
        Case("space in path, unquoted", run, ["scene=/tmp/my", "scene"], "scene"),
        Case("nsd-train max_steps abc", "nsd-train",
             [f"data.scene={base}", "trainer.max_steps=abc"], "max_steps"),
        Case("nsd-train lr -1", "nsd-train", [f"data.scene={base}", "optim.lr_encoder=-1"],
             "lr_encoder"),
        Case("nsd-export threshold 2", "nsd-export", ["checkpoint=/nonexistent.pt",
                                                      "threshold=2"], "threshold"),
        Case("nsd-eval max_frames -3", "nsd-eval", ["checkpoint=/nonexistent.pt",
                                                    "max_frames=-3"], "max_frames"),
        Case("nsd-synth individuals 0", "nsd-synth", ["num_individuals=0"], "num_individuals"),
        Case("nsd-synth image_size 0", "nsd-synth", ["image_size=[0,0]"], "image_size"),
        Case("netepu-train lr nan", "netepu-train", ["netepu.optim.lr=nan"], "lr"),
        Case("netepu-embed batch 0", "netepu-embed", ["export=/x", "checkpoint=/y",
                                                      "batch_size=0"], "batch_size"),
        Case("val_fraction 0 (every frame trains)", run, [*sc, "train.data.val_fraction=0"],
             "", expect="ok"),
        # ---- files
        Case("checkpoint holds a list", run, [*sc],
             "checkpoint", setup=_file("list.pt", lambda p: torch.save([1, 2], p))),
        Case("checkpoint is text", run, [*sc], "checkpoint",
             setup=_file("notes.pt", lambda p: p.write_text("hello"))),
        Case("checkpoint is a pickle payload", run, [*sc], "checkpoint",
             setup=_file("evil.pt", _pickle_payload)),
        Case("checkpoint missing", run, [*sc, "checkpoint=/nonexistent/ckpt.pt"], "ckpt.pt"),
        Case("out is an existing file", run, [*sc], "taken", setup=_out_is_file),
        Case("scene missing", run, ["scene=/nonexistent/scene"], "/nonexistent/scene"),
        Case("scene folder empty", run, [], "empty", setup=_empty),
        Case("dense=false scene, evaluation", run, [f"scene={nodense}"], "gt", expect="ok"),
        # ---- scenes
        Case("frame of another size", run, [], "cam1", setup=_edit(base, _resize_one)),
        Case("frame names disagree", run, [], "cam2", setup=_edit(base, _drop_frame)),
        Case("corrupt image", run, [], "cam3", setup=_edit(base, _corrupt)),
        Case("black frame", run, [], "cam0", expect="warning", setup=_edit(base, _blank(0))),
        Case("saturated frame", run, [], "cam0", expect="warning",
             setup=_edit(base, _blank(255))),
        Case("nothing moves", run, [], "moves", expect="warning", setup=_edit(base, _still)),
        Case("one camera", run, [], "camera", setup=_edit(base, _one_camera)),
        Case("calibration in mm", run, [], "millimetres", expect="warning",
             setup=_edit(base, _calib(_scaled(1e3)))),
        Case("calibration kilometres apart", run, [], "units=",
             setup=_edit(base, _calib(_scaled(1e6)))),
        Case("singular K", run, [], "cam0", setup=_edit(base, _calib(_singular))),
        Case("NaN in calibration", run, [], "cam0", setup=_edit(base, _calib(_nan_calib))),
        Case("camera without calibration", run, [], "cam3", expect="warning",
             setup=_edit(base, _calib(_drop_camera_calib))),
        Case("camera one frame short", run, [], "different numbers of frames",
             expect="warning", setup=_edit(base, _one_short)),
        Case("background plate of another size", run, [], "background plate",
             setup=_edit(base, _bad_plate)),
        Case("nsd-check, frame names disagree", "nsd-check", [], "cam2",
             setup=_edit(base, _drop_frame)),
        Case("nsd-check, blank frame", "nsd-check", [], "cam0", expect="warning",
             setup=_edit(base, _blank(0))),
        Case("second run on a busy out=", run, [*sc], "in use by", setup=_busy),
    ]
    return c


def _leftovers(work: Path) -> list[str]:
    return [str(p.relative_to(work)) for p in work.rglob("*.partial-*")]


def run_case(case: Case, root: Path) -> dict[str, object]:
    """Run one case in its own folder; returns the table row."""
    work = Path(tempfile.mkdtemp(prefix="case-", dir=root))
    extra = case.setup(work) if case.setup else []
    args = list(case.args) + extra
    if case.command == "nsd-run" and not any(a.startswith("out=") for a in args):
        args.append(f"out={work / 'run'}")
    if case.command == "nsd-run" and case.fast:
        args = FAST + args  # the case's own values come last and win
    if case.command in ("nsd-train", "netepu-train"):
        args = [f"hydra.run.dir={work / 'run'}", "trainer.max_steps=2", "trainer.max_minutes=0",
                *args]
    if case.command == "nsd-synth":
        args = [f"out={work / 'synth'}", "num_frames=2", *args]
    t0 = time.perf_counter()
    p = subprocess.run([str(BIN / case.command), *args], capture_output=True, text=True,
                       cwd=work, timeout=600, env={**os.environ, **case.extra_env})
    seconds = time.perf_counter() - t0
    text = p.stdout + p.stderr
    traceback = "Traceback (most recent call last)" in text
    errors = [ln for ln in p.stderr.splitlines() if ": error:" in ln]
    warnings = [ln for ln in text.splitlines() if "warning" in ln.lower()]
    if p.returncode not in (0, 2) or traceback:
        outcome = "crash"
    elif case.expect == "ok":
        outcome = "ok" if p.returncode == 0 else "refused"
    elif p.returncode == 2:
        outcome = ("clean error" if errors and case.culprit in errors[0]
                   else "error without culprit")
    elif case.expect == "warning" and any(case.culprit in w for w in warnings):
        outcome = "warning"
    else:
        outcome = "silent"
    msg = errors[0] if errors else (next((w for w in warnings if case.culprit in w), "")
                                    if case.expect == "warning" else "")
    if outcome == "crash":
        msg = (text.strip().splitlines() or [""])[-1]
    for owner in _OWNERS:  # the first run must be unharmed by the refused second one
        owner.communicate("\n", timeout=60)
        if owner.returncode != 0:
            outcome = "crash"
    _OWNERS.clear()
    left = _leftovers(work)
    return {"case": case.name, "command": case.command, "outcome": outcome,
            "exit": p.returncode, "leftovers": len(left), "seconds": round(seconds, 1),
            "message": msg.replace("|", "/")[:200]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="run the cases whose name contains this")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bad-input-"))
    base, nodense = root / "base", root / "nodense"
    for out, extra in ((base, []), (nodense, ["dense=false"])):
        subprocess.run([str(BIN / "nsd-synth"), f"out={out}", "num_frames=12",
                        "image_size=[64,64]", *extra], check=True, capture_output=True)
    rows = []
    for case in _cases(base, nodense):
        if args.only and args.only not in case.name:
            continue
        row = run_case(case, root)
        print(f"{row['outcome']:>22}  {case.name}: {row['message']}", flush=True)
        rows.append(row)
    shutil.rmtree(root, ignore_errors=True)
    if args.only:
        return
    counts = {k: sum(r["outcome"] == k for r in rows)
              for k in ("clean error", "warning", "ok", "error without culprit", "silent",
                        "refused", "crash")}
    write_report(
        "bad_input", "Bad input: what a user sees", rows,
        notes=("Each row is one command run in a fresh process (tools/bad_input.py). "
               "clean error: exit 2, one line naming the culprit, no traceback; warning: the "
               "run finishes and a warning names the culprit; ok: a case that must work "
               "(it used to crash); leftovers: `*.partial-*` folders left behind."),
        extra={"cases": len(rows), **counts},
    )
    print(counts)


if __name__ == "__main__":
    main()
