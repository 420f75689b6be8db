"""How many separate bodies the visual hull shows (nsd.cues.count), on hand-built voxels."""

from __future__ import annotations

import pytest
import torch

from nsd.cues.count import BODY_SHARE, QUANTILE, TOP_DROP, blobs, body_counts

UP = torch.tensor([0.0, 0.0, 1.0])


def _column(x: float, y: float, z0: float, n: int) -> list[list[float]]:
    """``n`` voxel centres (cell 1) stacked from height ``z0`` in the column at (x, y)."""
    return [[x + 0.5, y + 0.5, z0 + i + 0.5] for i in range(n)]


def _body(x: float, y: float, n: int = 10, z0: float = 0.0) -> list[list[float]]:
    """A 2 x 2 columns body ``n`` voxels high standing at (x, y)."""
    return [p for dx in (0, 1) for dy in (0, 1) for p in _column(x + dx, y + dy, z0, n)]


def test_blobs_join_pieces_across_one_empty_column_and_keep_bodies_apart():
    body = _body(0, 0)
    piece = _column(3, 0, 0, 4)  # one empty column (x = 2) between: the same blob
    other = _body(10, 10)
    noise = [[20.5, 20.5, 0.5]]  # a one-voxel column: no blob
    out = blobs(torch.tensor(body + piece + other + noise), UP, 1.0)
    assert out.tolist() == [[10.0, 9.5], [10.0, 9.5]]


def test_blobs_of_nothing():
    assert blobs(torch.zeros(0, 3), UP, 1.0).shape == (0, 2)
    assert blobs(torch.tensor([[0.5, 0.5, 0.5]]), UP, 1.0).shape == (0, 2)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_blobs_follow_the_up_direction(axis):
    """The same scene with another axis up gives the same blobs."""
    pts = torch.tensor(_body(0, 0) + _body(6, 0, n=4))
    up = torch.zeros(3)
    up[axis] = 1.0
    rotated = torch.zeros_like(pts)
    rotated[:, axis] = pts[:, 2]
    rest = [a for a in range(3) if a != axis]
    rotated[:, rest[0]], rotated[:, rest[1]] = pts[:, 0], pts[:, 1]
    out = blobs(rotated, up, 1.0)
    assert out[:, 0].tolist() == [10.0, 4.0]
    assert out[:, 1].tolist() == pytest.approx([9.5, 3.5])


def test_body_counts_drop_low_ghosts_and_cones_below_the_floor():
    """Bodies 10 voxels high standing on the floor (tops at 9.5): a column of fewer than
    BODY_SHARE x 10 voxels is a ghost, a blob whose top lies more than TOP_DROP x 10 cells
    below 9.5 is a cone under the floor; at either limit a blob counts."""
    n = 10
    assert BODY_SHARE * n == 4 and TOP_DROP * n == 5  # the limits this test is built on

    def count(*extra):
        return body_counts([blobs(torch.tensor(_body(0, 0) + _body(6, 0) + list(extra)), UP,
                                  1.0)] * 3, cell=1.0).tolist()[0]

    assert count() == 2
    assert count(*_column(12, 0, 0, 3)) == 2  # ghost: 3 voxels high
    assert count(*_column(12, 0, 6, 4)) == 3  # 4 high, top 9.5: at the column's limit
    assert count(*_body(12, 0, z0=-12)) == 2  # cone: full, top -2.5
    assert count(*_body(12, 0, z0=-5)) == 3  # top 4.5 = 9.5 - 5: at the top's limit
    assert count(*_body(12, 0, z0=-6)) == 2  # top 3.5


def test_touching_bodies_are_one_so_an_instant_only_undercounts():
    apart = blobs(torch.tensor(_body(0, 0) + _body(6, 0)), UP, 1.0)
    touching = blobs(torch.tensor(_body(0, 0) + _body(2, 0)), UP, 1.0)
    assert body_counts([apart, touching], cell=1.0).tolist() == [2, 1]


def test_the_scene_count_is_the_quantile_of_the_instants(monkeypatch):
    """scene_bodies on a stub: 89 of 100 instants show 1 body, 11 show 2: counted 2; 10 of
    99: counted 1 (the QUANTILE's lower value, the 89th of 99)."""
    from nsd.cues import count

    one = blobs(torch.tensor(_body(0, 0)), UP, 1.0)
    two = blobs(torch.tensor(_body(0, 0) + _body(6, 0)), UP, 1.0)
    script = [two] * 11 + [one] * 89  # per instant
    monkeypatch.setattr(count, "occupied_voxels",
                        lambda ev, grid: torch.arange(100) == ev)  # voxel t at instant t
    monkeypatch.setattr(count, "blobs", lambda pts, up, cell: script[int(pts)])

    class Grid:
        centres, up, size = torch.arange(100), UP, 1.0

    n, per = count.scene_bodies(lambda t: t, range(100), Grid)
    assert per.tolist() == [2] * 11 + [1] * 89
    assert QUANTILE == 0.9 and n == 2
    n, _ = count.scene_bodies(lambda t: t, range(1, 100), Grid)
    assert n == 1  # 10 of 99
