"""``nsd-eval``: the command line of :mod:`nsd.evaluation.checkpoint` (JSON, Markdown table)."""

from __future__ import annotations

import json
from pathlib import Path

import hydra
from omegaconf import DictConfig

from nsd.core.app import check_command_line, reported
from nsd.core.atomic import atomic_write_text
from nsd.core.errors import ConfigError
from nsd.core.threads import set_threads
from nsd.evaluation.checkpoint import evaluate_checkpoint, markdown_table
from nsd.evaluation.export_masks import export_mask_scores
from nsd.evaluation.labelled import LABEL_METRICS, score_labels
from nsd.evaluation.tracking import tracking_metrics
from nsd.inference.multiview import InferenceSettings
from nsd.io.footage import MultiViewFootage
from nsd.io.ground_truth import GroundTruth
from nsd.io.identities import identity_by_row
from nsd.io.labels import Labels2D, read_labels_2d
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
        labels, scene = None, None
        if cfg.export or cfg.labels:  # the scene of an export (the checkpoint's by default)
            scene = resolve_scene(
                cfg.scene or load_decomposition(cfg.checkpoint).config.data.scene)
            labels = _labels(cfg, scene)  # read and checked before any work
        metrics: dict[str, float] = {}
        if labels is None or GroundTruth.exists(scene):  # real footage: the labels alone
            metrics = evaluate_checkpoint(
                cfg.checkpoint, cfg.scene, frames, cfg.max_frames, cfg.refine, settings,
                baseline=bool(cfg.baseline), device=cfg.device,
            )
        if cfg.export and GroundTruth.exists(scene):
            tracks = tracking_metrics(cfg.export, scene)
            metrics.update({f"tracking_{k}": v for k, v in tracks.items()})
            metrics.update(export_mask_scores(cfg.export, scene))  # at native resolution
        if labels is not None:
            row_ids = identity_by_row(Path(cfg.identities)) if cfg.identities else None
            scores = score_labels(cfg.export, labels, row_ids)
            metrics.update({f"labels_{k}": v for k, v in scores.items()})
        ckpt = Path(cfg.checkpoint)
        out = Path(cfg.out) if cfg.out else (ckpt if ckpt.is_dir() else ckpt.parent)
        atomic_write_text(out / "eval.json", json.dumps(metrics, indent=2))
        table = markdown_table(metrics) + _export_tables(metrics)
        atomic_write_text(out / "eval.md", table)
        print(table)
        return float(metrics.get("mask_miou", float("nan")))


def _labels(cfg: DictConfig, scene: Path) -> Labels2D | None:
    """The labelled keypoints of ``labels=`` (None without), with what they need."""
    if not cfg.labels:
        return None
    if not cfg.export:
        raise ConfigError("labels= scores an export: give export=<nsd-export folder of the scene>")
    return read_labels_2d(cfg.labels, MultiViewFootage(scene).calibration_names)


def _export_tables(metrics: dict[str, float]) -> str:
    """The export's own figures: masks at native resolution, labelled keypoints."""
    rows = []
    if "native_miou" in metrics:
        rows += ["", "The export's masks at native resolution (nsd/evaluation/export_masks.py):",
                 "", "| metric | value |", "|---|---|"]
        rows += [f"| {k} | {metrics[k]:.4g} |"
                 for k in ("native_miou", "native_boundary_f", "native_instances")]
    if "labels_keypoints_in_mask" in metrics:
        rows += ["", "Against the labelled keypoints (nsd/evaluation/labelled.py):", "",
                 "| metric | value |", "|---|---|"]
        rows += [f"| {k} | {metrics[f'labels_{k}']:.4g} |" for k in LABEL_METRICS]
    return "\n".join(rows) + "\n" if rows else ""


def main() -> None:
    """Entry point of ``nsd-eval``: the command line is checked before any work."""
    check_command_line(PROG, "eval")
    _hydra_main()


if __name__ == "__main__":
    main()
