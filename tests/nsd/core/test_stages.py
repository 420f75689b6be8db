"""Pipeline stages: finished stages are skipped, config changes re-run downstream."""

from __future__ import annotations

from pathlib import Path

import pytest

from nsd.core.stages import Stage, StageRunner


def _stages(calls, a_value=1):
    def run_a(out, up):
        calls.append("a")
        (out / "a.txt").write_text(str(a_value))
        return {"value": a_value}

    def run_b(out, up):
        calls.append("b")
        v = up["a"].summary["value"] * 10
        (out / "b.txt").write_text(str(v))
        return {"value": v}

    return [Stage("a", run_a, {"x": a_value}), Stage("b", run_b, {}, needs=("a",))]


def test_rerun_does_no_work(tmp_path):
    calls = []
    runner = StageRunner(tmp_path)
    for s in _stages(calls):
        runner.run(s)
    assert calls == ["a", "b"] and (tmp_path / "b" / "b.txt").read_text() == "10"
    calls.clear()
    again = StageRunner(tmp_path)
    res = [again.run(s) for s in _stages(calls)]
    assert calls == [] and all(r.skipped for r in res)
    assert res[1].summary == {"value": 10}


def test_config_change_reruns_downstream(tmp_path):
    calls = []
    runner = StageRunner(tmp_path)
    for s in _stages(calls):
        runner.run(s)
    calls.clear()
    runner = StageRunner(tmp_path)
    for s in _stages(calls, a_value=2):
        runner.run(s)
    assert calls == ["a", "b"] and (tmp_path / "b" / "b.txt").read_text() == "20"


def test_failed_stage_leaves_no_folder_and_is_retried(tmp_path):
    def boom(out, up):
        (out / "half.txt").write_text("x")
        raise RuntimeError("stage failed")

    runner = StageRunner(tmp_path)
    with pytest.raises(RuntimeError, match="stage failed"):
        runner.run(Stage("c", boom))
    assert not (tmp_path / "c").exists()
    assert runner.done(Stage("c", boom)) is None


def test_disabled_stage_is_recorded(tmp_path):
    runner = StageRunner(tmp_path)
    r = runner.run(Stage("d", lambda o, u: {}, enabled=False, why_disabled="one subject"))
    assert r.skipped and r.summary == {"disabled": "one subject"}
    assert not (tmp_path / "d").exists()


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
def test_each_stage_records_its_own_peak_memory(tmp_path):
    """A stage that touches 300 MiB peaks that much above a small stage run after it: the
    peak is reset per stage (not the process's high-water mark so far)."""
    import json

    import numpy as np

    def big(out, up):
        a = np.ones(300 * 2**20, np.uint8)  # touched, so resident
        return {"sum": int(a[::4096].sum())}

    runner = StageRunner(tmp_path)
    first = runner.run(Stage("big", big))
    second = runner.run(Stage("small", lambda out, up: {"n": 1}))
    assert first.peak_rss_mb - second.peak_rss_mb > 250
    assert json.loads((tmp_path / "big" / "stage.json").read_text())["peak_rss_mb"] == \
        first.peak_rss_mb
    assert runner.run(Stage("big", big)).peak_rss_mb is None  # done earlier: nothing measured
