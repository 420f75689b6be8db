"""The label-free quality report: the other cameras' hull, identity figures, the stage."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.cameras.calibration import CameraRig
from nsd.cameras.projection import project_points
from nsd.cues.occupancy import voxel_grid
from nsd.evaluation.quality import _identity_figures, _warnings, reprojected_hulls
from tests.conftest import look_at_camera

SIZE = (64, 64)


def _rig(n=4):
    return CameraRig([
        look_at_camera(f"c{i}", np.array([4 * np.cos(2 * np.pi * i / n),
                                          4 * np.sin(2 * np.pi * i / n), 2.0]),
                       np.array([0.0, 0.0, 0.8]), f=60.0, size=SIZE)
        for i in range(n)])  # fmt: skip


def _ball_masks(rig, centre, radius=0.4):
    """Silhouettes of a ball (V, H, W)."""
    rng = np.random.default_rng(0)
    g = rng.normal(size=(20000, 3))  # points filling the ball, splatted into every view
    pts = centre + radius * g / np.linalg.norm(g, axis=1, keepdims=True) * \
        rng.uniform(0, 1, (20000, 1)) ** (1 / 3)
    out = []
    for cam in rig:
        p = cam.tensors(torch.float64)
        uv, _ = project_points(torch.from_numpy(pts), p["K"], p["R"], p["t"], p["dist"])
        m = np.zeros((SIZE[1], SIZE[0]), bool)
        u, v = uv.numpy().round().astype(int).T
        ok = (u >= 0) & (u < SIZE[0]) & (v >= 0) & (v < SIZE[1])
        m[v[ok], u[ok]] = True
        out.append(m)
    assert all(m.sum() > 30 for m in out)
    return np.stack(out)


def test_the_other_cameras_confirm_a_consistent_mask_and_not_a_stray_one():
    rig = _rig()
    masks = _ball_masks(rig, np.array([0.3, -0.2, 0.9]))
    grid = voxel_grid(rig, SIZE[::-1], 64)
    hulls = reprojected_hulls(masks, grid, dilate=1)
    covered = [(masks[v] & hulls[v]).sum() / masks[v].sum() for v in range(4)]
    assert min(covered) > 0.95  # a real body: every view's mask is inside the others' hull
    stray = masks.copy()
    stray[2, 2:12, 2:12] = True  # something only camera 2 sees, far from the ball
    hulls2 = reprojected_hulls(stray, grid, dilate=1)
    assert not (hulls2[2] & ~masks[2])[2:12, 2:12].any()  # the others do not confirm it
    share = (stray[2] & hulls2[2]).sum() / stray[2].sum()
    assert share == pytest.approx(masks[2].sum() / stray[2].sum(), abs=0.05)
    # more foreground in one view can only grow the hulls it takes part in
    assert (hulls2[0] & masks[0]).sum() >= (hulls[0] & masks[0]).sum()


def _ann(i, cam, frame, subject):
    return {"id": i, "camera": cam, "frame": frame, "subject_id": subject}


def test_identity_figures_known_values():
    anns, k = [], 0
    for t in range(4):
        for cam in ("a", "b"):
            for s in (1, 2):
                k += 1
                anns.append(_ann(k, cam, t, s))
    ident = {a["id"]: a["subject_id"] - 1 for a in anns}
    fig = _identity_figures({"annotations": anns}, ident, [0, 1, 2, 3])
    assert fig["identity_switches"] == 0 and fig["view_agreement"] == 1
    assert fig["count_changes"] == 0 and fig["subjects_median"] == 2
    assert fig["individuals"] == 2
    # camera b's track of subject 1 takes identity 1 at frame 2 only: two switches along its
    # 3 steps (of 4 tracks x 3 steps), and the two cameras disagree on that subject then
    swap = next(a["id"] for a in anns if (a["camera"], a["frame"], a["subject_id"]) == ("b", 2, 1))
    ident[swap] = 1
    fig = _identity_figures({"annotations": anns}, ident, [0, 1, 2, 3])
    assert fig["identity_switches"] == pytest.approx(2 / 12)
    assert fig["view_agreement"] == pytest.approx(7 / 8)
    assert fig["count_changes"] == 0  # frame 2 still holds identities {0, 1}
    # frame 3 loses subject 2 in both cameras: the count changes once in three steps
    drop = [a["id"] for a in anns if a["frame"] == 3 and a["subject_id"] == 2]
    for i in drop:
        ident[i] = -1  # no identity: left out
    fig = _identity_figures({"annotations": anns}, ident, [0, 1, 2, 3])
    assert fig["count_changes"] == pytest.approx(1 / 3)
    # without identities the tracks' own ids are used: nothing switches
    fig = _identity_figures({"annotations": anns}, None, [0, 1, 2, 3])
    assert fig["identity_switches"] == 0 and np.isnan(fig["individuals"])
    # both subjects named as one (two bodies in one identity): one individual
    ident = {a["id"]: 0 for a in anns}
    assert _identity_figures({"annotations": anns}, ident, [0, 1, 2, 3])["individuals"] == 1


def test_fewer_individuals_than_told_warn():
    """The identities naming fewer individuals than the run was told of warn, naming both
    counts; as many, or no count told (an upper bound), or no identities (NaN), do not."""
    fine = {"explained": 1.0, "spill": 0.0, "consistency": 1.0, "identity_switches": 0.0,
            "view_agreement": 1.0, "count_changes": 0.0, "explained/a": 1.0}
    got = _warnings({**fine, "individuals": 3.0}, ["a"], 4)
    assert len(got) == 1 and "name 3 individuals" in got[0] and "told of 4" in got[0]
    assert _warnings({**fine, "individuals": 4.0}, ["a"], 4) == []
    assert _warnings({**fine, "individuals": 3.0}, ["a"], None) == []
    assert _warnings({**fine, "individuals": float("nan")}, ["a"], 4) == []


def test_fewer_individuals_than_the_hull_shows_warn():
    """Fewer identities than the visual hull's separate bodies warn, whatever the run was told
    (five individuals run with two windows name 2); as many or more, a hull not counted (NaN)
    or no identities (NaN) do not; the warning of a told count comes first, alone."""
    fine = {"explained": 1.0, "spill": 0.0, "consistency": 1.0, "identity_switches": 0.0,
            "view_agreement": 1.0, "count_changes": 0.0, "explained/a": 1.0}
    got = _warnings({**fine, "individuals": 2.0, "hull_bodies": 4.0}, ["a"], 2)
    assert len(got) == 1 and "name 2 individuals" in got[0] and "at least 4" in got[0]
    assert _warnings({**fine, "individuals": 2.0, "hull_bodies": 4.0}, ["a"], None) == got
    assert _warnings({**fine, "individuals": 4.0, "hull_bodies": 4.0}, ["a"], None) == []
    assert _warnings({**fine, "individuals": 5.0, "hull_bodies": 4.0}, ["a"], None) == []
    assert _warnings({**fine, "individuals": 2.0, "hull_bodies": float("nan")}, ["a"], 2) == []
    assert _warnings({**fine, "individuals": float("nan"), "hull_bodies": 4.0}, ["a"], 2) == []
    told = _warnings({**fine, "individuals": 2.0, "hull_bodies": 4.0}, ["a"], 3)
    assert len(told) == 1 and "told of 3" in told[0]


def test_short_footage_is_not_counted(tiny_scene):
    """The tiny scene (2 cameras, a few frames): the hull's bodies are not counted (NaN)."""
    from nsd.evaluation.quality import _hull_bodies
    from nsd.io.footage import MultiViewFootage

    footage = MultiViewFootage(tiny_scene, None, (32, 24))
    assert np.isnan(_hull_bodies(footage, torch.zeros(2, 3, 24, 32), 48, "auto"))


def test_the_report_says_what_the_hull_shows_beside_the_identities():
    from nsd.evaluation.quality import QualityReport, quality_markdown

    base = {"frames": 1.0, "explained": 1.0, "spill": 0.0, "consistency": 1.0,
            "identity_switches": 0.0, "view_agreement": 1.0, "count_changes": 0.0,
            "explained/a": 1.0, "consistency/a": 1.0}

    def said(bodies: float, named: float) -> str:
        report = QualityReport(["a"], [], {**base, "hull_bodies": bodies,
                                           "individuals": named}, [])
        return next(line for line in quality_markdown(report, []).splitlines()
                    if "hull" in line)

    assert said(4.0, 5.0) == ("The visual hull shows at least 4 separate bodies; the "
                              "identities name 5 individuals.")
    assert said(float("nan"), 2.0).startswith("The visual hull's bodies were not counted")
    assert said(3.0, float("nan")) == "The visual hull shows at least 3 separate bodies."
