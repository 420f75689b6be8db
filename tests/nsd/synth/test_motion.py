"""Motion: trajectories stay in the area, never interpenetrate, respect joint limits."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.synth.body import GROUND_CLEARANCE, make_individual
from nsd.synth.motion import MotionConfig, _gap, gait_angles, sample_pose, simulate_motion
from nsd.synth.skeleton import BIPED, QUADRUPED
from tests.base import assert_close


@pytest.fixture(scope="module")
def herd():
    return [
        make_individual("biped", 0, seed=1),
        make_individual("quadruped", 1, seed=1),
        make_individual("biped", 2, seed=1),
    ]


def _simulate(herd, interaction="free", seed=0, T=250):
    cfg = MotionConfig.defaults(interaction=interaction, area_radius=2.0)
    return simulate_motion(herd, T, 25.0, cfg, np.random.default_rng(seed)), cfg


def test_inside_area_and_never_interpenetrating(herd):
    trajs, cfg = _simulate(herd)
    T = len(trajs[0])
    xy = np.stack([t.poses.translation[:, :2].numpy() for t in trajs], 1)
    head = np.stack([t.poses.heading.numpy() for t in trajs], 1)
    assert np.linalg.norm(xy, axis=-1).max() <= cfg.area_radius + 1e-9
    for t in range(T):
        for i, j in itertools.combinations(range(len(herd)), 2):
            gap, _ = _gap(herd[i], xy[t, i], head[t, i], herd[j], xy[t, j], head[t, j])
            assert gap > -0.02, (t, i, j, gap)
    # they move: each covers more than a metre
    assert (np.abs(np.diff(xy, axis=0)).sum((0, 2)) > 1.0).all()


def test_joint_limits_and_ground_contact(herd):
    trajs, _ = _simulate(herd)
    for ind, tr in zip(herd, trajs, strict=True):
        lim = torch.as_tensor(ind.species.joint_limits)
        a = tr.poses.angles
        assert (a >= lim[..., 0] - 1e-12).all() and (a <= lim[..., 1] + 1e-12).all()
        low = ind.posed(tr.poses).lowest_point()
        assert_close(low, torch.full_like(low, GROUND_CLEARANCE))


def test_deterministic_per_seed(herd):
    a, _ = _simulate(herd, seed=3, T=40)
    b, _ = _simulate(herd, seed=3, T=40)
    c, _ = _simulate(herd, seed=4, T=40)
    assert torch.equal(a[1].poses.angles, b[1].poses.angles)
    assert not torch.equal(a[1].poses.angles, c[1].poses.angles)


def test_close_interaction_brings_individuals_together():
    pair = [make_individual("biped", i, seed=1) for i in range(2)]

    def mean_gap(interaction: str) -> float:
        gaps = []
        for seed in range(3):
            trajs, _ = _simulate(pair, interaction, seed)
            xy = np.stack([t.poses.translation[:, :2].numpy() for t in trajs], 1)
            hd = np.stack([t.poses.heading.numpy() for t in trajs], 1)
            gaps += [_gap(pair[0], xy[t, 0], hd[t, 0], pair[1], xy[t, 1], hd[t, 1])[0]
                     for t in range(len(xy))]  # fmt: skip
        return float(np.mean(gaps))

    free, close = mean_gap("free"), mean_gap("close")
    assert close < 0.6 * free, (close, free)


def test_gait_is_periodic_and_legs_alternate():
    phase = np.array([0.3, 0.3 + 2 * np.pi, 0.3 + np.pi])
    a = gait_angles(BIPED, phase, np.ones(3))
    assert np.allclose(a[0], a[1])
    lh, rh = BIPED.index("left_hip"), BIPED.index("right_hip")
    assert np.isclose(a[0, lh, 1], a[2, rh, 1]) and np.isclose(a[0, lh, 1], -a[0, rh, 1])
    q = gait_angles(QUADRUPED, phase, np.zeros(3))
    assert np.abs(q).max() == 0  # standing still: no gait


def test_sample_pose_is_plausible():
    ind = make_individual("quadruped", 0)
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = sample_pose(ind, rng, position=(1.0, -2.0))
        assert p.angles.shape == (25, 3)
        assert_close(p.translation[:2], torch.tensor([1.0, -2.0], dtype=torch.float64))
        assert_close(
            ind.posed(p).lowest_point(), torch.tensor(GROUND_CLEARANCE, dtype=torch.float64)
        )


@pytest.mark.parametrize(
    "changes, key",
    [({"interaction": "fight"}, "motion.interaction"), ({"area_radius": 0.0}, "motion.area_radius"),
     ({"pose_variation": -1.0}, "motion.pose_variation")],
)  # fmt: skip
def test_bad_motion_config(changes, key):
    with pytest.raises(ConfigError, match=key):
        MotionConfig.defaults(**changes)


def test_area_too_small(herd):
    cfg = MotionConfig.defaults(interaction="free", area_radius=0.3)
    with pytest.raises(ConfigError, match="area_radius"):
        simulate_motion(herd, 5, 25.0, cfg, np.random.default_rng(0))
