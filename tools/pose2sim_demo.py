"""Turn a Pose2Sim demo (multi- or single-person) into a scene folder.

The demos (BSD-3-Clause, by David Pagnon) ship inside the ``pose2sim`` package on
the package registry: four synchronised portrait videos (1088x1920 at 60 fps) and a
Qualisys calibration each. The multi-person demo (the default) shows two people, the
second composited into the videos by the demo's authors; the single-person demo one.

    python tools/pose2sim_demo.py scenes/pose2sim          # download + convert
    python tools/pose2sim_demo.py scenes/pose2sim_single --demo single
    python tools/pose2sim_demo.py scenes/pose2sim --wheel pose2sim-0.10.49-py3-none-any.whl

The scene folder gets ``cam01.mp4 .. cam04.mp4``, ``calibration.toml`` (converted
from ``Calib.qca.txt`` to OpenCV conventions, metres) and ``source/`` with the
original calibration and licence. Nothing is written under the final name until
the whole scene is in place. The videos are never committed to the repository.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_qca, write_toml
from nsd.core.atomic import atomic_directory

PACKAGE = "pose2sim==0.10.49"
DEMOS = {"multi": "Pose2Sim/Demo_MultiPerson", "single": "Pose2Sim/Demo_SinglePerson"}
NOTES = {"multi": "The second person in these videos was composited in by the demo's authors.\n",
         "single": ""}
CAMERAS = ("cam01", "cam02", "cam03", "cam04")
MAX_PADDING = 16  # pixels a video may lack against its calibration (a codec's block padding)
DEFAULT_CACHE = Path.home() / ".cache" / "nsd" / "pose2sim"


def download_wheel(cache: Path = DEFAULT_CACHE) -> Path:
    """``pip download --no-deps pose2sim==0.10.49`` into ``cache``; returns the wheel."""
    hits = sorted(cache.glob("pose2sim-0.10.49-*.whl"))
    if hits:
        return hits[0]
    cache.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--quiet",
        "--disable-pip-version-check",
        "-d",
        str(cache),
        PACKAGE,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    hits = sorted(cache.glob("pose2sim-0.10.49-*.whl"))
    if proc.returncode != 0 or not hits:
        raise RuntimeError(
            f"could not download {PACKAGE} with pip (exit {proc.returncode}): "
            f"{proc.stderr.strip()[-500:]}"
        )
    return hits[0]


def build_scene(out: Path, wheel: Path | None = None, overwrite: bool = False,
                demo: str = "multi") -> Path:
    """Write the scene folder ``out`` of ``demo`` (a key of :data:`DEMOS`) atomically;
    returns ``out``."""
    if demo not in DEMOS:
        raise ValueError(f"demo must be one of {sorted(DEMOS)}, got {demo!r}")
    DEMO = DEMOS[demo]
    out = Path(out)
    if out.exists() and not overwrite and (out / "calibration.toml").is_file():
        return out
    wheel = Path(wheel) if wheel else download_wheel()
    with zipfile.ZipFile(wheel) as zf, atomic_directory(out, overwrite=True) as tmp:
        names = set(zf.namelist())
        wanted = [f"{DEMO}/videos/{c}.mp4" for c in CAMERAS]
        wanted += [f"{DEMO}/calibration/Calib.qca.txt"]
        missing = [w for w in wanted if w not in names]
        if missing:
            raise RuntimeError(f"{wheel} lacks {missing}: not the expected pose2sim release")
        for c in CAMERAS:
            (tmp / f"{c}.mp4").write_bytes(zf.read(f"{DEMO}/videos/{c}.mp4"))
        (tmp / "source").mkdir()
        qca = tmp / "source" / "Calib.qca.txt"
        qca.write_bytes(zf.read(f"{DEMO}/calibration/Calib.qca.txt"))
        lic = [n for n in names if n.endswith(("LICENSE", "LICENSE.txt", "LICENSE.md"))]
        if lic:
            (tmp / "source" / "LICENSE").write_bytes(zf.read(lic[0]))
        (tmp / "source" / "README.txt").write_text(
            f"Converted from {wheel.name} ({DEMO}) by tools/pose2sim_demo.py.\n" + NOTES[demo]
        )
        rig = read_qca(qca)
        notes, cameras = [], []
        for cam in rig:  # codec padding: the calibration's sensor vs the stored videos
            cap = cv2.VideoCapture(str(tmp / f"{cam.name}.mp4"))
            size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            cap.release()
            if cam.size is not None and size != tuple(cam.size):
                if max(abs(a - b) for a, b in zip(size, cam.size, strict=True)) > MAX_PADDING:
                    raise RuntimeError(f"{DEMO} {cam.name}: the calibration is {cam.size} but "
                                       f"the video {size}: not a codec's padding")
                notes.append(f"{cam.name}: calibrated {cam.size[0]}x{cam.size[1]}, video "
                             f"{size[0]}x{size[1]}; size set to the video's, K kept")
                cam = dataclasses.replace(cam, size=size)
            cameras.append(cam)
        rig = CameraRig(cameras, source=rig.source)
        if notes:
            with open(tmp / "source" / "README.txt", "a") as f:
                f.write("The calibration's image size is the sensor's; the videos are "
                        "assumed to have lost a codec's padding at the right/bottom edge:\n"
                        + "\n".join(notes) + "\n")
        write_toml(rig, tmp / "calibration.toml")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="scene folder to write")
    ap.add_argument("--wheel", type=Path, help="use this pose2sim wheel instead of downloading")
    ap.add_argument("--overwrite", action="store_true", help="rebuild an existing scene folder")
    ap.add_argument("--demo", choices=sorted(DEMOS), default="multi",
                    help="which demo: multi (two people, the default) or single (one person)")
    args = ap.parse_args(argv)
    print(build_scene(args.out, args.wheel, args.overwrite, args.demo))


if __name__ == "__main__":
    main()
