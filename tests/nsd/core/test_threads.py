"""torch threads default to every core the process may use (nsd/core/threads.py)."""

from __future__ import annotations

import os

import pytest
import torch

from nsd.core.threads import available_cores, set_threads


@pytest.fixture(autouse=True)
def _restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_zero_means_every_core_of_the_affinity_mask():
    assert available_cores() == len(os.sched_getaffinity(0))
    assert set_threads(0) == available_cores() == torch.get_num_threads()


def test_a_torchrun_job_shares_the_cores(monkeypatch):
    monkeypatch.setenv("LOCAL_WORLD_SIZE", str(available_cores() + 5))
    assert set_threads(0) == 1  # never below one
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")
    assert set_threads(0) == available_cores()


def test_a_given_count_is_used_and_a_negative_one_refused():
    assert set_threads(1) == 1 == torch.get_num_threads()
    with pytest.raises(ValueError, match="threads must be >= 0"):
        set_threads(-1)
