"""Full maps: candidate region, and culled / coarse-to-fine renders against dense ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from netepu.geometry.maps import BACKGROUND_LOGIT, MapSettings, candidate_region, render_maps
from netepu.geometry.renderer import RenderContext, ViewFrame
from tests.base import BaseTester

W, H = 96, 72


def _context(centres: list[tuple[float, float]], scale: float = 20.0) -> RenderContext:
    """A frame holding one 'keypoint' per image at ``centres`` (no network needed)."""
    B = len(centres)
    uv = torch.tensor(centres, dtype=torch.float64).reshape(B, 1, 2)
    return RenderContext(
        ViewFrame(uv, torch.full((B, 1), 5.0, dtype=torch.float64), uv[:, 0],
                  torch.full((B,), scale, dtype=torch.float64),
                  torch.full((B,), 5.0, dtype=torch.float64), 1.0,
                  torch.zeros(B, 1, 3, dtype=torch.float64)), {})


def disc_query(radius: float = 14.0):
    """An analytic renderer: a disc of ``radius`` px around the keypoint, linear fields inside."""
    calls = []

    def query(ctx, uv):
        calls.append(uv.shape[0] * uv.shape[1])
        c = ctx.frame.uv[:, :1]
        d = (uv - c).norm(dim=-1)
        return {"logit": 3.0 * (radius - d), "depth_norm": 0.01 * (uv[..., 0] - c[..., 0]),
                "nnopcs": torch.stack([uv[..., 0] / W, uv[..., 1] / H,
                                       0.5 + 0 * uv[..., 0]], -1)}

    return query, calls


class TestCandidateRegion(BaseTester):
    def test_single_point_is_a_disc(self):
        region = candidate_region(np.array([[40.0, 30.0]]), 20.0, 0.5, (W, H))
        assert region[30, 40] and region[30, 49] and not region[30, 52]
        assert abs(region.sum() - math.pi * 10**2) < 0.08 * math.pi * 10**2

    def test_contains_the_hull(self):
        pts = np.array([[10.0, 10.0], [80.0, 15.0], [50.0, 60.0]])
        region = candidate_region(pts, 10.0, 0.0, (W, H))
        assert region[30, 50]  # inside the triangle
        assert all(region[int(y), int(x)] for x, y in pts)
        assert not region[65, 5]

    def test_outside_image_is_empty(self):
        assert not candidate_region(np.array([[-500.0, -500.0]]), 10.0, 1.0, (W, H)).any()


class TestRenderMaps(BaseTester):
    def test_dense_known_values(self):
        q, _ = disc_query()
        maps = render_maps(q, _context([(40.0, 30.0)]), (W, H), MapSettings.defaults(mode="dense"))
        yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        inside = ((xx - 40.0) ** 2 + (yy - 30.0) ** 2).sqrt() < 14.0
        assert torch.equal(maps.silhouette[0], inside)
        self.assert_close(maps.nnopcs[0, 30, 40], torch.tensor([40 / W, 30 / H, 0.5],
                                                               dtype=torch.float64))
        assert maps.evaluated.tolist() == [W * H]
        assert (maps.depth[0][~inside] == 0).all()
        self.assert_close(maps.depth[0, 30, 50], torch.tensor(5.0 + 0.1, dtype=torch.float64))

    @pytest.mark.parametrize("levels", [1, 2, 3])
    def test_coarse_to_fine_matches_dense(self, levels):
        q, calls = disc_query()
        ctx = _context([(40.0, 30.0), (61.3, 40.7)])
        dense = render_maps(q, ctx, (W, H), MapSettings.defaults(mode="dense"))
        c2f = render_maps(q, ctx, (W, H), MapSettings.defaults(mode="coarse_to_fine", margin=1.0,
                                                      levels=levels))
        assert torch.equal(c2f.silhouette, dense.silhouette)
        fg = dense.silhouette
        # fields are linear: bilinear interpolation of the interior is exact
        self.assert_close(c2f.nnopcs[fg], dense.nnopcs[fg])
        self.assert_close(c2f.depth[fg], dense.depth[fg])
        assert (c2f.evaluated < 0.5 * dense.evaluated).all()
        calls.clear()
        s = MapSettings.defaults(mode="coarse_to_fine", margin=1.0, levels=levels)
        render_maps(q, ctx, (W, H), s)
        assert sum(calls) >= int(c2f.evaluated.sum())  # padded batches hold every evaluation

    def test_culled_only_evaluates_region(self):
        q, _ = disc_query()
        ctx = _context([(40.0, 30.0)])
        maps = render_maps(q, ctx, (W, H), MapSettings.defaults(mode="culled", margin=1.0))
        region = candidate_region(np.array([[40.0, 30.0]]), 20.0, 1.0, (W, H))
        assert int(maps.evaluated[0]) == int(region.sum())
        assert (maps.logit[0][~torch.from_numpy(region)] == BACKGROUND_LOGIT).all()

    def test_small_margin_cuts_the_silhouette(self):
        q, _ = disc_query()
        maps = render_maps(q, _context([(40.0, 30.0)]), (W, H),
                           MapSettings.defaults(mode="culled", margin=0.3))  # 6 px < 14 px disc
        assert maps.silhouette.sum() < math.pi * 7**2

    def test_bad_settings(self):
        with pytest.raises(ValueError, match="mode"):
            MapSettings.defaults(mode="fast").validate()


@pytest.mark.parametrize("stride", [1, 2, 4, 8])
def test_coarse_points_are_the_grid_points_whose_cells_meet_the_region(stride):
    from netepu.geometry.maps import _coarse_points

    rng = np.random.default_rng(stride)
    fy, fx = 5 * stride + 1, 3 * stride + 1
    region = torch.from_numpy(rng.random((2, fy, fx)) > 0.97)
    got = _coarse_points(region, stride)
    want = torch.zeros(2, 6, 4, dtype=torch.bool)  # slow reference: look at the four cells
    for b in range(2):
        for i in range(6):
            for j in range(4):
                y0, y1 = max(0, (i - 1) * stride), min(fy, (i + 1) * stride + 1)
                x0, x1 = max(0, (j - 1) * stride), min(fx, (j + 1) * stride + 1)
                want[b, i, j] = bool(region[b, y0:y1, x0:x1].any())
    assert torch.equal(got, want)
