"""Shared helpers for the benchmark scripts under ``tools/``.

Every benchmark writes two files under ``docs/benchmarks/``: ``<name>.md`` (a
Markdown table for people) and ``<name>.json`` (the same figures for machines),
both stamped with the date, the git commit and the machine. Timings are medians
of repeated runs measured in one process, so ratios between rows are fair even
on a noisy machine.
"""

from __future__ import annotations

import csv
import datetime as _dt
import json
import os
import platform
import statistics
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from nsd.core.atomic import atomic_write_text
from nsd.core.memory import peak_rss_mb  # one reader of VmHWM, re-exported for the benchmarks

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = ROOT / "docs" / "benchmarks"

__all__ = ["BENCH_DIR", "evaluations", "machine_info", "median_time", "peak_rss_mb", "ship_file",
           "write_report"]


def git_commit(ignore: Sequence[Path] = ()) -> str:
    """The short hash of HEAD, with ``+dirty`` when a tracked file differs from it (the files
    in ``ignore`` excepted: a tool that writes a tracked file, such as a shipped model and its
    manifest, is not made dirty by its own output); ``unknown`` without git."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "-z", "--untracked-files=no", "--no-renames"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        )
        skip = {Path(p).resolve() for p in ignore}
        changed = [entry[3:] for entry in dirty.stdout.split("\0") if entry]  # "XY path"
        dirty_files = [f for f in changed if (ROOT / f).resolve() not in skip]
        return out.stdout.strip() + ("+dirty" if dirty_files else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine_info() -> dict[str, Any]:
    """CPU model, core count, memory, Python/torch versions and thread count."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        mem_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gb,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
    }


def ship_file(manifest_path: Path, manifest: dict, section: str, key: str, target: Path,
              digest: str, made: dict[str, Any]) -> None:
    """Record a shipped model file in ``manifest[section][key]`` (its name, SHA-256, size,
    ``made``, the torch build, CPU, commit and date) and write the manifest atomically. The
    commit is not called dirty for ``target`` and the manifest, which the tool itself wrote."""
    machine = machine_info()
    manifest.setdefault(section, {})[key] = {
        "file": target.name, "sha256": digest, "bytes": target.stat().st_size, **made,
        "torch": machine["torch"], "machine": machine["cpu"],
        "commit": git_commit(ignore=(target, manifest_path)),
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    atomic_write_text(manifest_path, json.dumps(manifest, indent=2) + "\n")
    print(f"wrote {target} ({target.stat().st_size / 1e6:.1f} MB, sha256 {digest[:16]}...)")


def evaluations(run: Path, key: str = "eval/heldout_poses/iou") -> list[dict[str, str]]:
    """The evaluation rows of the ``metrics.csv`` in the run folder ``run`` (``netepu-train``
    writes one), the rows where ``key`` is logged, one per step in the order logged: the final
    evaluation, which repeats the last step's, is kept once. Values are the file's strings
    ("" where a column was not logged)."""
    with (run / "metrics.csv").open(newline="") as f:
        rows = {r["step"]: r for r in csv.DictReader(f) if r.get(key)}
    return list(rows.values())


def median_time(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeats`` runs after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if v == 0 or 1e-3 <= abs(v) < 1e5:
            return f"{v:.4g}"
        return f"{v:.3e}"
    return str(v)


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of ``rows``; columns are the union of keys, in first-seen order."""
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def write_report(
    name: str,
    title: str,
    rows: Sequence[dict[str, Any]],
    notes: str = "",
    extra: dict[str, Any] | None = None,
    out_dir: Path = BENCH_DIR,
) -> tuple[Path, Path]:
    """Write ``<name>.md`` and ``<name>.json`` with a stamp (date, commit, machine).

    Args:
        name: file stem.
        title: heading of the Markdown file.
        rows: the table; columns are the union of keys, in first-seen order.
        notes: Markdown paragraph(s) printed under the table.
        extra: more figures for the JSON file (and listed in the Markdown).
    """
    stamp = {
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "commit": git_commit(),
        "machine": machine_info(),
    }
    lines = [f"# {title}", ""]
    m = stamp["machine"]
    lines.append(
        f"Measured {stamp['date']} at commit `{stamp['commit']}` on {m['cpu']} "
        f"({m['cores']} cores, {m['memory_gib']} GiB, torch {m['torch']}, "
        f"{m['torch_threads']} threads)."
    )
    lines.append("")
    if rows:
        lines += [markdown_table(rows), ""]
    if extra:
        for k, v in extra.items():
            if not isinstance(v, (dict, list)):
                lines.append(f"- **{k}**: {_fmt(v)}")
        lines.append("")
    if notes:
        lines += [notes.strip(), ""]
    out_dir.mkdir(parents=True, exist_ok=True)
    md, js = out_dir / f"{name}.md", out_dir / f"{name}.json"
    atomic_write_text(md, "\n".join(lines))
    atomic_write_text(
        js,
        json.dumps(
            {**stamp, "title": title, "rows": list(rows), "extra": extra or {}},
            indent=2,
            default=str,
        ),
    )
    return md, js
