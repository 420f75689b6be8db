"""``nsd-synth``: write a synthetic scene folder with full ground truth (Hydra app).

Settings are those of ``conf/synth.yaml`` (documented there and in
``datasets/synthetic.md``); override any on the command line::

    nsd-synth out=scenes/demo num_individuals=3 species='[biped,quadruped]'
    nsd-synth out=scenes/cows species='[quadruped]' rig.kind=nepumoo motion.interaction=free

Without ``out`` the scene goes to ``scenes/synth-<config hash>``. Bad values
exit with status 2 and a message naming the key.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from nsd.core.app import check_command_line, reported
from nsd.synth.config import SceneConfig
from nsd.synth.scene import CLI_KEYS, write_scene

__all__ = ["main", "run"]

PROG = "nsd-synth"


def run(cfg: DictConfig | dict) -> Path:
    """Write the scene described by a composed ``synth`` config; returns its folder."""
    values = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    out, overwrite = values.get("out"), bool(values.get("overwrite", False))
    config = SceneConfig.from_dict({k: v for k, v in values.items() if k not in CLI_KEYS})
    path = Path(out) if out else Path("scenes") / f"synth-{config.hash()}"
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=true to replace it")
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if done == total or done % max(1, total // 10) == 0:
            print(f"\rrendered {done}/{total} frames", end="", file=sys.stderr, flush=True)

    write_scene(config, path, overwrite=overwrite, progress=progress)
    print(file=sys.stderr)
    print(f"wrote {path} in {time.perf_counter() - t0:.1f} s (see {path / 'gt' / 'preview.png'})")
    return path


@hydra.main(config_path="pkg://nsd.conf", config_name="synth", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    with reported(PROG):
        run(cfg)


def main() -> None:
    """Entry point of ``nsd-synth``; bad input exits with status 2 and one line."""
    check_command_line(PROG, "synth")
    _hydra_main()


if __name__ == "__main__":
    main()
