"""Crops: known windows, exact resampling on the identity window, chunked files and index."""

from __future__ import annotations

import numpy as np
import pytest

from nsd.io.crops import CropWriter, cut_crop, read_crop_index, read_crops, square_crop_box


def test_square_crop_box_known_values():
    assert square_crop_box([10, 20, 10, 40], 0.0) == (-5.0, 20.0, 40.0)
    assert square_crop_box([0, 0, 8, 4], 0.5) == (-4.0, -6.0, 16.0)


def test_identity_window_returns_the_image():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
    mask = rng.random((16, 16)) > 0.5
    crop, m = cut_crop(img, mask, (0.0, 0.0, 16.0), 16)
    np.testing.assert_array_equal(crop, img)
    np.testing.assert_array_equal(m.astype(bool), mask)


def test_half_size_window_and_black_outside():
    img = np.full((16, 8, 3), 200, np.uint8)
    mask = np.zeros((16, 8), bool)
    mask[:4, :4] = True
    crop, m = cut_crop(img, mask, (-8.0, 0.0, 16.0), 8)  # left half outside the frame
    assert (crop[:, :4] == 0).all() and (crop[:, 4:] == 200).all()
    assert m[:2, 4:6].all() and m.sum() == 4  # output pixels sample x, y = 0.5, 2.5, ...


def test_writer_chunks_and_index_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    mask = np.zeros((30, 40), bool)
    mask[5:20, 10:18] = True
    w = CropWriter(tmp_path / "crops", size=12, chunk=2)
    made = [w.add(i + 1, 7, "cam0", i, img, mask, [10, 5, 8, 15], 0.1) for i in range(5)]
    w.close()
    assert w.count == 5 and w.files == 3
    index = read_crop_index(tmp_path / "crops")
    assert [r["file"] for r in index] == ["crops-000000.npz"] * 2 + ["crops-000001.npz"] * 2 + [
        "crops-000002.npz"
    ]
    assert index[3]["row"] == 1 and index[3]["frame"] == 3 and index[3]["subject_id"] == 7
    assert index[0]["crop_side"] == pytest.approx(15 * 1.2)
    crops, masks = read_crops(tmp_path / "crops", [4, 1])
    np.testing.assert_array_equal(crops[0], made[3][0])
    np.testing.assert_array_equal(masks[1], made[0][1])
    assert crops.shape == (2, 12, 12, 3) and masks.dtype == np.uint8
    with pytest.raises(KeyError, match="no crops for ids"):
        read_crops(tmp_path / "crops", [99])


def test_a_chunk_that_cannot_be_written_stops_the_writer(tmp_path):
    """Chunks are written by a thread; its error (here: the folder became a file) is raised
    by the writer, not lost."""
    import shutil

    img = np.zeros((8, 8, 3), np.uint8)
    w = CropWriter(tmp_path / "crops", size=4, chunk=1)
    shutil.rmtree(tmp_path / "crops")
    (tmp_path / "crops").write_text("not a folder")
    with pytest.raises(OSError):
        w.add(1, 1, "cam0", 0, img, np.ones((8, 8), bool), [0, 0, 8, 8], 0.0)
        w.close()
