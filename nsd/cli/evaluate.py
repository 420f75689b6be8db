"""``nsd-eval``: the command line of :mod:`nsd.evaluation.checkpoint` (JSON, Markdown table)."""

from __future__ import annotations

import json
from pathlib import Path

import hydra
from omegaconf import DictConfig

from nsd.core.app import check_command_line, reported
from nsd.core.atomic import atomic_write_text
from nsd.core.threads import set_threads
from nsd.evaluation.checkpoint import evaluate_checkpoint, markdown_table
from nsd.evaluation.tracking import tracking_metrics
from nsd.inference.multiview import InferenceSettings
from nsd.io.scenes import resolve_scene
from nsd.model.checkpoint import load_decomposition

__all__ = ["main"]

PROG = "nsd-eval"


@hydra.main(config_path="pkg://nsd.conf", config_name="eval", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    with reported(PROG):
        set_threads(int(cfg.threads))
        frames = cfg.frames if isinstance(cfg.frames, str) else list(cfg.frames)
        settings = InferenceSettings.from_config(cfg.inference)
        metrics = evaluate_checkpoint(
            cfg.checkpoint, cfg.scene, frames, cfg.max_frames, cfg.refine, settings,
            baseline=bool(cfg.baseline),
        )
        if cfg.export:
            scene = cfg.scene or load_decomposition(cfg.checkpoint).config.data.scene
            tracks = tracking_metrics(cfg.export, resolve_scene(scene))
            metrics.update({f"tracking_{k}": v for k, v in tracks.items()})
        ckpt = Path(cfg.checkpoint)
        out = Path(cfg.out) if cfg.out else (ckpt if ckpt.is_dir() else ckpt.parent)
        atomic_write_text(out / "eval.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "eval.md", markdown_table(metrics))
        print(markdown_table(metrics))
        return float(metrics.get("mask_miou", float("nan")))


def main() -> None:
    """Entry point of ``nsd-eval``: the command line is checked before any work."""
    check_command_line(PROG, "eval")
    _hydra_main()


if __name__ == "__main__":
    main()
