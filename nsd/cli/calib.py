"""``nsd-calib``: a calibration as a table, converted to another format, or drawn
(:mod:`nsd.io.calibration_preview`), so that a wrong calibration shows before training."""

from __future__ import annotations

from pathlib import Path

import cv2
import hydra
from omegaconf import DictConfig

from nsd.cameras.calibration_io import read_calibration, write_calibration
from nsd.core.app import check_command_line, reported
from nsd.core.atomic import atomic_write_bytes
from nsd.core.errors import NSDError
from nsd.io.calibration_preview import preview, rig_table
from nsd.io.frame_sources import find_source

__all__ = ["main"]

PROG = "nsd-calib"


def _first_frames(scene: Path, rig) -> list:
    """Each camera's first frame at its calibrated size, where the scene has footage."""
    frames = []
    for cam in rig:
        try:
            img = find_source(scene, cam.name).read(0)
        except NSDError:
            img = None
        if img is not None and cam.size and (img.shape[1], img.shape[0]) != tuple(cam.size):
            img = cv2.resize(img, tuple(cam.size), interpolation=cv2.INTER_AREA)
        frames.append(img)
    return frames


@hydra.main(config_path="pkg://nsd.conf", config_name="calib", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    with reported(PROG):
        source = Path(cfg.calibration).expanduser()
        rig = read_calibration(source, cfg.units)
        print(f"{PROG}: {rig.source}: {len(rig)} cameras\n")
        print(rig_table(rig))
        if cfg.convert:
            fmt = write_calibration(rig, Path(cfg.convert).expanduser(), str(cfg.format))
            print(f"{PROG}: wrote {cfg.convert} ({fmt})")
        if cfg.preview:
            frames = _first_frames(source, rig) if source.is_dir() else None
            _, buf = cv2.imencode(".png", cv2.cvtColor(preview(rig, frames), cv2.COLOR_RGB2BGR))
            atomic_write_bytes(Path(cfg.preview).expanduser(), buf.tobytes())
            print(f"{PROG}: wrote {cfg.preview}")


def main() -> None:
    """Entry point of ``nsd-calib``."""
    check_command_line(PROG, "calib")
    _hydra_main()


if __name__ == "__main__":
    main()
