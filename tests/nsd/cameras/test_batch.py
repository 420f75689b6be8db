"""The batched camera type (nsd/cameras/batch.py): selection, repetition, files, projection."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.cameras.batch import CameraBatch
from nsd.cameras.calibration import CameraRig
from nsd.cameras.projection import project_points
from tests.conftest import look_at_camera


def _rig() -> CameraRig:
    return CameraRig(
        [
            look_at_camera(
                f"c{i}",
                np.array([3 * np.cos(a), 3 * np.sin(a), 1.5]),
                np.array([0.0, 0.0, 1.0]),
                dist=np.array([0.05 * i, -0.01, 0.0, 0.0, 0.0]),
            )
            for i, a in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False))
        ]
    )


def test_stacked_projects_as_each_camera_alone():
    rig = _rig()
    cams = rig.stacked(torch.float64)
    X = torch.tensor([[0.1, -0.2, 1.0], [0.3, 0.2, 0.6]], dtype=torch.float64)
    uv, _ = project_points(X.expand(len(cams), -1, -1), cams.K, cams.R, cams.t, cams.dist)
    for v, cam in enumerate(rig):
        ref, _ = cam.project(X.numpy())
        np.testing.assert_allclose(uv[v].numpy(), ref, atol=1e-9)


def test_indexing_selects_views_and_keeps_a_batch():
    cams = _rig().stacked(torch.float32)
    pick = cams[torch.tensor([3, 1])]
    assert len(pick) == 2
    assert torch.equal(pick.R, cams.R[[3, 1]]) and torch.equal(pick.dist, cams.dist[[3, 1]])
    assert len(cams[2]) == 1 and torch.equal(cams[2].t, cams.t[2:3])
    assert torch.equal(cams[-1].K, cams.K[-1:])


def test_repeat_cat_and_dtype():
    cams = _rig().stacked(torch.float32)
    rep = cams.repeat(3)
    assert len(rep) == 12 and torch.equal(rep.K[4:8], cams.K)  # [c0..c3, c0..c3, ...]
    both = CameraBatch.cat([cams[0:2], cams[2:]])
    assert torch.equal(both.t, cams.t) and torch.equal(both.dist, cams.dist)
    assert cams.to(torch.float64).K.dtype == torch.float64
    no_dist = CameraBatch(cams.K, cams.R, cams.t)
    assert CameraBatch.cat([no_dist, cams]).dist is None


def test_files_round_trip_and_bad_mappings_are_errors():
    cams = _rig().stacked(torch.float32)
    arrays = {k: v.numpy() for k, v in cams.as_dict().items()}
    back = CameraBatch.from_mapping(arrays)
    assert all(torch.equal(getattr(back, k), getattr(cams, k)) for k in ("K", "R", "t", "dist"))
    assert CameraBatch.from_mapping(cams) is cams
    with pytest.raises(ValueError, match=r"missing \['t'\]"):
        CameraBatch.from_mapping({"K": arrays["K"], "R": arrays["R"]})
