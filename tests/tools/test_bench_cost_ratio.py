"""The cost ratio's reading of our learning curve (tools/bench_cost_ratio.py)."""

import pytest

from tools.bench_cost_ratio import minutes_to_reach

CURVE = [{"minutes": m, "heldout_poses/iou": y}
         for m, y in ((1.0, 0.6), (2.0, 0.8), (3.0, 0.7), (4.0, 0.9))]  # fmt: skip


def test_interpolates_between_evaluations():
    assert minutes_to_reach(CURVE, 0.7) == (pytest.approx(1.5), True)
    # the dip at 3 minutes counts as the best so far (0.8): 0.85 lies between 3 and 4 minutes
    assert minutes_to_reach(CURVE, 0.85) == (pytest.approx(3.5), True)


def test_below_the_first_evaluation_is_only_a_bound_and_beyond_the_last_is_none():
    assert minutes_to_reach(CURVE, 0.3) == (1.0, False)
    assert minutes_to_reach(CURVE, 0.95) == (None, False)
