"""The analytic ray caster against slow, obviously-correct references."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.synth.body import make_individual
from nsd.synth.motion import sample_pose
from nsd.synth.raycast import (
    Ellipsoids,
    camera_rays,
    cast_rays,
    intersect_cylinder_inside,
    intersect_ellipsoids,
    intersect_ground,
)
from nsd.synth.render import render_views
from nsd.synth.rigs import look_at
from tests.base import assert_close

GOLDEN = (np.sqrt(5) - 1) / 2


def _reference_entry(o: np.ndarray, d: np.ndarray, c, M, a, s_max: float = 30.0) -> np.ndarray:
    """First root of g(s) = |M^T (o + s d - c) / a|^2 - 1 by golden section + bisection.

    Independent of the closed form: finds the minimum of the convex g numerically,
    then bisects [0, s_min] for the sign change. o, d: (R, 3); c (P, 3), M (P, 3, 3),
    a (P, 3). Returns (R, P) distances, inf when missed. float64 numpy.
    """

    def g(s):
        x = o[:, None, :] + s[..., None] * d[:, None, :] - c[None]
        u = np.einsum("rpi,pij->rpj", x, M) / a[None]
        return (u * u).sum(-1) - 1.0

    R, P = o.shape[0], c.shape[0]
    lo, hi = np.zeros((R, P)), np.full((R, P), s_max)
    for _ in range(90):  # golden-section search for the minimum
        x1, x2 = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
        left = g(x1) < g(x2)
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
    s_min = 0.5 * (lo + hi)
    hit = g(s_min) < 0
    lo, hi = np.zeros((R, P)), s_min.copy()
    for _ in range(70):  # bisection: g(lo) > 0 >= g(hi)
        mid = 0.5 * (lo + hi)
        inside = g(mid) < 0
        hi = np.where(inside, mid, hi)
        lo = np.where(inside, lo, mid)
    return np.where(hit, 0.5 * (lo + hi), np.inf)


@pytest.fixture
def scene():
    """A biped and a quadruped in random poses, one in front of the other."""
    rng = np.random.default_rng(3)
    a = make_individual("biped", identity=0, seed=1)
    b = make_individual("quadruped", identity=1, seed=1)
    pa = sample_pose(a, rng, position=(0.9, 0.3))
    pb = sample_pose(b, rng, position=(-1.0, -0.8))
    return [a, b], [pa, pb]


@pytest.fixture
def cameras():
    return [
        look_at("plain", (4.0, 1.0, 1.6), (-0.3, 0.0, 0.8), (40, 30), fov_deg=38),
        look_at("distorted", (-1.0, 4.5, 2.2), (-0.3, 0.0, 0.7), (40, 30), fov_deg=45,
                dist=(-0.25, 0.08, 0.002, -0.001, -0.01)),
    ]  # fmt: skip


class TestDepthInvariant:
    def test_rendered_depth_is_the_distance_along_the_ray(self, scene, cameras):
        """Z * |(x, y, 1)| equals an independent per-pixel intersection, per pixel."""
        inds, poses = scene
        out = render_views(inds, poses, cameras, background=False)
        bodies = [i.posed(p.to(torch.float64)) for i, p in zip(inds, poses, strict=True)]
        c = torch.cat([b.centres for b in bodies]).numpy()
        M = torch.cat([b.axes for b in bodies]).numpy()
        a = torch.cat([b.radii for b in bodies]).numpy()
        owner = np.concatenate([np.full(b.centres.shape[0], n) for n, b in enumerate(bodies)])
        for v, cam in enumerate(cameras):
            W, H = cam.size
            vv, uu = np.mgrid[0:H, 0:W]
            uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
            d = cam.unproject(uv)  # unit world rays (distortion removed by OpenCV maths)
            ref = _reference_entry(np.repeat(cam.center[None], len(uv), 0), d, c, M, a)
            ref_s = ref.min(1)
            ref_owner = np.where(np.isfinite(ref_s), owner[ref.argmin(1)], -1)
            z = out["depth"][v].numpy().ravel().astype(np.float64)
            d_cam = d @ cam.R.T
            s = z / d_cam[:, 2]  # Z * |(x, y, 1)| = Z / cos: distance along the unit ray
            hit = np.isfinite(z)
            assert hit.sum() > 50, "camera sees too little of the bodies"
            agree = hit == np.isfinite(ref_s)
            assert (~agree).sum() <= 2  # only grazing silhouette pixels may differ
            both = hit & np.isfinite(ref_s)
            np.testing.assert_allclose(s[both], ref_s[both], rtol=0, atol=2e-5)
            inst = out["instance"][v].numpy().ravel()
            assert (inst[both] == ref_owner[both]).all()

    def test_cast_equals_brute_force_without_culling(self, scene, cameras):
        inds, poses = scene
        E = Ellipsoids.concat(
            [
                (b.centres, b.axes, b.radii)
                for b in (i.posed(p) for i, p in zip(inds, poses, strict=True))
            ]
        )
        rays = camera_rays(cameras)
        index, dirs = rays.flat()
        hits = cast_rays(rays.origins, index, dirs, E)
        R, P = dirs.shape[0], E.centres.shape[0]
        rr, pp = torch.meshgrid(torch.arange(R), torch.arange(P), indexing="ij")
        rr, pp = rr.ravel(), pp.ravel()
        s, _, _ = intersect_ellipsoids(
            rays.origins[index[rr]], dirs[rr], E.centres[pp], E.axes[pp], E.radii[pp]
        )
        s = s.view(R, P)
        best, arg = s.min(1)
        assert_close(hits.distance, best)
        hit = torch.isfinite(best)
        assert torch.equal(hits.owner[hit], E.owner[arg[hit]])
        assert torch.equal(hits.owner[~hit], torch.full_like(hits.owner[~hit], -1))
        # amodal: per individual minimum
        for n in range(E.num_individuals):
            sn = torch.where(E.owner[None] == n, s, torch.inf).min(1).values
            assert_close(hits.owner_distance[:, n], sn)


class TestRays:
    def test_rays_honour_distortion(self, cameras):
        """A world point projected (with distortion) lies on the ray of its pixel."""
        cam = cameras[1]
        rng = np.random.default_rng(0)
        X = rng.uniform(-1, 1, (30, 3)) + np.array([-0.3, 0.0, 0.8])
        uv, _ = cam.project(X)
        rays = camera_rays([cam], dtype=torch.float64)
        # ray through a non-integer pixel: build it the same way as camera_rays
        from nsd.cameras.projection import pixel_to_normalized

        p = cam.tensors(torch.float64)
        xy = pixel_to_normalized(torch.as_tensor(uv), p["K"], p["dist"]).numpy()
        d = np.c_[xy, np.ones(len(xy))] @ cam.R
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        to_x = X - cam.center
        cross = np.cross(d, to_x / np.linalg.norm(to_x, axis=1, keepdims=True))
        assert np.abs(cross).max() < 1e-9
        # and camera_rays at integer pixels matches the same construction
        u0 = np.array([[7.0, 11.0]])
        xy0 = pixel_to_normalized(torch.as_tensor(u0), p["K"], p["dist"]).numpy()
        d0 = np.c_[xy0, [1.0]] @ cam.R
        assert_close(rays.directions[0, 11, 7], torch.as_tensor(d0[0] / np.linalg.norm(d0)))
        assert_close(
            rays.z_per_distance[0, 11, 7], torch.tensor(1 / np.linalg.norm(np.r_[xy0[0], 1.0]))
        )

    def test_supersample_middle_sample_is_the_pixel_centre(self, cameras):
        r1 = camera_rays(cameras, supersample=1, dtype=torch.float64)
        r3 = camera_rays(cameras, supersample=3, dtype=torch.float64)
        assert r3.directions.shape[1:3] == (90, 120)
        assert_close(r3.centre_samples(r3.directions), r1.directions)

    @pytest.mark.parametrize("bad", [0, 2, -1])
    def test_bad_supersample(self, cameras, bad):
        with pytest.raises(ConfigError, match="supersample"):
            camera_rays(cameras, supersample=bad)

    def test_bad_image_size(self, cameras):
        with pytest.raises(ConfigError, match="image_size"):
            camera_rays(cameras, image_size=(0, 10))


class TestPlanes:
    def test_ground_known_values(self):
        o = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
        d = torch.tensor([[0.0, 0.6, -0.8], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
        s = intersect_ground(o, d)
        assert_close(s[0], torch.tensor(2.5, dtype=torch.float64))
        assert torch.isinf(s[1:]).all()  # upward ray; origin below the ground

    def test_cylinder_from_inside(self):
        o = torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, 1.0], [20.0, 0.0, 1.0]], dtype=torch.float64)
        d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
        s = intersect_cylinder_inside(o, d, 5.0)
        assert_close(s[0], torch.tensor(4.0, dtype=torch.float64))
        assert torch.isinf(s[1:]).all()  # vertical ray; origin outside
