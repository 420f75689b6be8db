"""Pipeline stages: finished stages are skipped, config changes re-run downstream."""

from __future__ import annotations

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
