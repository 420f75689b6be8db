"""``nsd-export``: the command line of :mod:`nsd.export.subjects` (Hydra app, ``conf/export.yaml``).

SIGTERM unwinds like Ctrl-C, so an interrupted export leaves no half-written folder.
"""

from __future__ import annotations

import signal
import sys

import hydra
from omegaconf import DictConfig

from nsd.core.errors import NSDError
from nsd.export.subjects import run

__all__ = ["main"]


def _terminate(signum, frame) -> None:
    raise SystemExit(128 + signum)  # unwinds atomic_directory, which removes the partial folder


@hydra.main(config_path="pkg://nsd.conf", config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """Entry point of ``nsd-export``; bad input exits with status 2 and a message."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        run(cfg)
    except (NSDError, FileExistsError) as e:
        print(f"nsd-export: error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
