"""Image grids (nsd/evaluation/visualise.py)."""

from __future__ import annotations

import numpy as np

from nsd.evaluation.visualise import grid


def test_grid_places_each_image_and_takes_cameras_of_other_sizes():
    """Cells as large as the largest image, each image at its cell's top left, white between;
    the Pose2Sim single-person demo has cameras 108 and 109 pixels wide at panel size."""
    a = np.full((4, 5, 3), 10, np.uint8)
    b = np.full((4, 6, 3), 20, np.uint8)
    c = np.full((3, 6, 3), 30, np.uint8)
    out = grid([[a, b], [c]], pad=1)
    assert out.shape == (2 * (4 + 1) + 1, 2 * (6 + 1) + 1, 3)
    assert (out[1:5, 1:6] == 10).all() and (out[1:5, 6] == 255).all()  # a, then its padding
    assert (out[1:5, 8:14] == 20).all()
    assert (out[6:9, 1:7] == 30).all() and (out[9, 1:7] == 255).all()
    assert (out[6:10, 8:14] == 255).all()  # the missing second column of row 2
