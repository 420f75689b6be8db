"""Resumable pipeline stages: a finished stage is never recomputed.

A stage writes its outputs into ``<run>/<name>/`` atomically (built under a
temporary name and renamed on success, see :mod:`nsd.core.atomic`) together with a
``stage.json`` marker that records the stage's inputs (its config, the hashes of
the stages it depends on) and its outputs' summary. A stage is *done* when its
folder holds a marker whose input hash (its config, its upstream stages' results and the
toolkit's version) equals the current one; then it is skipped and its recorded result is
returned. Changing a stage's config (or an
upstream stage's result) re-runs it and everything downstream.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import nsd
from nsd.core.atomic import atomic_directory
from nsd.core.memory import peak_rss_mb, reset_peak_rss

__all__ = ["Stage", "StageResult", "StageRunner", "config_hash"]

log = logging.getLogger(__name__)
MARKER = "stage.json"


def config_hash(obj: Any) -> str:
    """Stable short hash of a JSON-serialisable object."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class StageResult:
    """What a stage produced.

    Attributes:
        name: stage name.
        folder: its output folder.
        summary: small JSON-serialisable figures (counts, metrics, paths).
        seconds: wall time of the run that produced it (0 if it was skipped now).
        skipped: True when an earlier run's result was reused.
        input_hash: hash of the stage's inputs.
        peak_rss_mb: the process's peak resident memory while the stage ran (MiB; None if
            it was skipped now).
    """

    name: str
    folder: Path
    summary: dict[str, Any]
    seconds: float
    skipped: bool
    input_hash: str
    peak_rss_mb: float | None = None


@dataclass
class Stage:
    """One step of a pipeline.

    Attributes:
        name: folder name under the run folder.
        run: ``run(out_dir, upstream) -> summary``; writes into ``out_dir`` (a temporary
            folder renamed to ``<run>/<name>`` on success); ``upstream`` maps the names of
            ``needs`` to their :class:`StageResult`.
        config: the stage's own settings (part of its input hash).
        needs: names of the stages it depends on.
        enabled: a disabled stage is recorded as skipped with summary ``{"disabled": ...}``.
    """

    name: str
    run: Callable[[Path, dict[str, StageResult]], dict[str, Any]]
    config: dict[str, Any] = field(default_factory=dict)
    needs: tuple[str, ...] = ()
    enabled: bool = True
    why_disabled: str = ""


class StageRunner:
    """Runs stages in order into a run folder, skipping the finished ones."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.results: dict[str, StageResult] = {}

    def _input_hash(self, stage: Stage) -> str:
        upstream = {n: self.results[n].input_hash + config_hash(self.results[n].summary)
                    for n in stage.needs}
        # a new toolkit version re-runs every stage: its code may compute them differently
        return config_hash({"config": stage.config, "upstream": upstream,
                            "toolkit": nsd.__version__})

    def done(self, stage: Stage) -> StageResult | None:
        """The recorded result if the stage is finished with the current inputs."""
        marker = self.root / stage.name / MARKER
        if not marker.is_file():
            return None
        rec = json.loads(marker.read_text())
        if rec.get("input_hash") != self._input_hash(stage):
            return None
        return StageResult(stage.name, marker.parent, rec["summary"], 0.0, True,
                           rec["input_hash"])

    def run(self, stage: Stage) -> StageResult:
        missing = [n for n in stage.needs if n not in self.results]
        if missing:
            raise RuntimeError(f"stage '{stage.name}' needs {missing}, which have not run")
        h = self._input_hash(stage)
        if not stage.enabled:
            res = StageResult(stage.name, self.root / stage.name,
                              {"disabled": stage.why_disabled or True}, 0.0, True, h)
            self.results[stage.name] = res
            log.info("stage %s: disabled (%s)", stage.name, stage.why_disabled)
            return res
        prev = self.done(stage)
        if prev is not None:
            log.info("stage %s: done earlier, skipped", stage.name)
            self.results[stage.name] = prev
            return prev
        t0 = time.perf_counter()
        log.info("stage %s: running", stage.name)
        reset_peak_rss()
        with atomic_directory(self.root / stage.name) as tmp:
            summary = stage.run(tmp, {n: self.results[n] for n in stage.needs})
            seconds, peak = time.perf_counter() - t0, round(peak_rss_mb(), 1)
            (tmp / MARKER).write_text(json.dumps(
                {"stage": stage.name, "input_hash": h, "config": stage.config,
                 "summary": summary, "seconds": seconds, "peak_rss_mb": peak},
                indent=2, default=str))
        res = StageResult(stage.name, self.root / stage.name, summary, seconds, False, h, peak)
        self.results[stage.name] = res
        return res
