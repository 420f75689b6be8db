"""Front and back from the direction of travel (netepu/pipeline/travel.py): known facings and
velocities, and fits turned front to back on the shared synthetic world put right."""

from __future__ import annotations

import numpy as np
import pytest

from netepu.pipeline.travel import face_travel, facing, travel_velocity
from nsd.synth.skeleton import BIPED, QUADRUPED

UP = np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("species", [BIPED, QUADRUPED])
def test_the_rest_pose_faces_forward_and_its_mirror_backward(species):
    """The species are built facing +x with their left along +y: the facing is +x, and the
    same points labelled the other way round face -x."""
    left, mirror = species.left_index(), species.mirror_index()
    f = facing(species.rest, left, mirror, UP)
    assert f[0] > 0.1 and abs(f[1]) < 1e-9 and f[2] == 0
    np.testing.assert_allclose(facing(species.rest[list(mirror)], left, mirror, UP), -f)


def test_a_fit_against_its_travel_is_relabelled_only_when_fast_enough():
    left, mirror = BIPED.left_index(), BIPED.mirror_index()
    rest = BIPED.rest
    backwards = np.array([-1.0, 0.0, 0.0])
    kp, flip = face_travel(rest, backwards, left, mirror, UP, 0.5)
    assert flip
    np.testing.assert_array_equal(kp, rest[list(mirror)])
    for velocity, speed in ((-backwards, 0.5), (0.3 * backwards, 0.5), (None, 0.5),
                            (backwards, 0.0)):
        kp, flip = face_travel(rest, velocity, left, mirror, UP, speed)
        assert not flip and kp is rest


def test_the_travel_is_the_ground_velocity_between_the_frames_around():
    positions = {(8, 1): (np.array([0.0, 0.0, 0.0]), 2),
                 (12, 1): (np.array([0.4, -0.2, 0.3]), 3)}
    v = travel_velocity(positions, 10, 1, 2, 25.0, UP)
    np.testing.assert_allclose(v, [0.4 * 25 / 4, -0.2 * 25 / 4, 0.0])  # height change dropped
    assert travel_velocity(positions, 10, 2, 2, 25.0, UP) is None  # another subject
    assert travel_velocity(positions, 11, 1, 2, 25.0, UP) is None  # an end missing


def test_fits_turned_front_to_back_are_put_right_on_the_synthetic_world(world):
    """The true poses of the shared world's walkers, every one turned front to back, go
    through the keypoints stage's relabelling: every fit it relabels becomes the true pose
    again, and a moving subject's are (its walkers face their travel)."""
    from netepu.pipeline.subject_keypoints import _face_travel
    from nsd.cameras.calibration_io import read_calibration

    with np.load(world["scene"] / "gt" / "keypoints3d.npz") as z:
        truth = {int(k.split("_")[1]): z[k] for k in z.files}
    mirror = list(BIPED.mirror_index())
    fits = [(t, ident + 1, [], kp[t][mirror], 1.0)  # the world's export: subject = identity + 1
            for ident, kp in truth.items() for t in range(1, len(kp) - 1)]
    rig = read_calibration(world["scene"])
    out, flips = _face_travel(fits, world["export"], world["scene"], rig, 1e-3, 5.0,
                              "biped", UP)  # 5 frames/s: d = 1 frame
    assert sum(flips) >= len(fits) // 2
    for (t, sid, _, kp, _), flip in zip(out, flips, strict=True):
        if flip:
            np.testing.assert_allclose(kp, truth[sid - 1][t], atol=1e-6)
    unchanged, none = _face_travel(fits, world["export"], world["scene"], rig, 0.0, 5.0,
                                   "biped", UP)
    assert not any(none) and unchanged is fits
