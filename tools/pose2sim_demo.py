"""Turn the Pose2Sim multi-person demo into a scene folder.

The demo (BSD-3-Clause, by David Pagnon) ships inside the ``pose2sim`` package on
the package registry: four synchronised portrait videos (1088x1920, 100 frames at
60 fps) of two people and a Qualisys calibration. Its second person was
composited into the videos by the demo's authors.

    python tools/pose2sim_demo.py scenes/pose2sim          # download + convert
    python tools/pose2sim_demo.py scenes/pose2sim --wheel pose2sim-0.10.49-py3-none-any.whl

The scene folder gets ``cam01.mp4 .. cam04.mp4``, ``calibration.toml`` (converted
from ``Calib.qca.txt`` to OpenCV conventions, metres) and ``source/`` with the
original calibration and licence. Nothing is written under the final name until
the whole scene is in place. The videos are never committed to the repository.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from pathlib import Path

from nsd.cameras.calibration_io import read_qca, write_toml
from nsd.core.atomic import atomic_directory

PACKAGE = "pose2sim==0.10.49"
DEMO = "Pose2Sim/Demo_MultiPerson"
CAMERAS = ("cam01", "cam02", "cam03", "cam04")
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


def build_scene(out: Path, wheel: Path | None = None, overwrite: bool = False) -> Path:
    """Write the demo scene folder ``out`` (atomically); returns ``out``."""
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
            f"Converted from {wheel.name} ({DEMO}) by tools/pose2sim_demo.py.\n"
            "The second person in these videos was composited in by the demo's authors.\n"
        )
        write_toml(read_qca(qca), tmp / "calibration.toml")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="scene folder to write")
    ap.add_argument("--wheel", type=Path, help="use this pose2sim wheel instead of downloading")
    ap.add_argument("--overwrite", action="store_true", help="rebuild an existing scene folder")
    args = ap.parse_args(argv)
    print(build_scene(args.out, args.wheel, args.overwrite))


if __name__ == "__main__":
    main()
