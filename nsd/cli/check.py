"""``nsd-check``: a scene folder checked before any long work (:mod:`nsd.io.scene_check`).

Exit status 0 with the scene's figures and any warnings, 2 with one line naming the
file, camera or frame that stops it.
"""

from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from nsd.core.app import check_command_line, reported
from nsd.io.scene_check import check_scene
from nsd.io.scenes import resolve_scene

__all__ = ["main"]

PROG = "nsd-check"


@hydra.main(config_path="pkg://nsd.conf", config_name="check", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s", force=True)
    with reported(PROG):
        scene = resolve_scene(cfg.scene)
        check = check_scene(scene, list(cfg.cameras) if cfg.cameras else None,
                            units=cfg.units, background=cfg.background)
        sizes = ", ".join(f"{k} {w}x{h}" for k, (w, h) in check.sizes.items())
        print(f"{PROG}: {scene}: {len(check.cameras)} cameras ({sizes}), {check.frames} frames, "
              f"cameras a median {check.camera_spacing:.2f} m apart; "
              f"{len(check.warnings)} warning(s)")
        for w in check.warnings:  # Hydra's logging set-up silences the module loggers here
            print(f"  warning: {w}")


def main() -> None:
    """Entry point of ``nsd-check``."""
    check_command_line(PROG, "check")
    _hydra_main()


if __name__ == "__main__":
    main()
