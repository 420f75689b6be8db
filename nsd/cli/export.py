"""``nsd-export``: the command line of :mod:`nsd.export.subjects` (Hydra app, ``conf/export.yaml``).

SIGTERM unwinds like Ctrl-C, so an interrupted export leaves no half-written folder.
"""

from __future__ import annotations

import signal

import hydra
from omegaconf import DictConfig

from nsd.core.app import check_command_line, reported
from nsd.export.subjects import run

__all__ = ["main"]

PROG = "nsd-export"


def _terminate(signum, frame) -> None:
    raise SystemExit(128 + signum)  # unwinds atomic_directory, which removes the partial folder


@hydra.main(config_path="pkg://nsd.conf", config_name="export", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    signal.signal(signal.SIGTERM, _terminate)
    with reported(PROG):
        run(cfg)


def main() -> None:
    """Entry point of ``nsd-export``; bad input exits with status 2 and one line."""
    check_command_line(PROG, "export")
    _hydra_main()


if __name__ == "__main__":
    main()
