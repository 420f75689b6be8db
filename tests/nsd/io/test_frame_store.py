"""Training frames on disk behind a memory map (nsd/io/frame_store.py)."""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pytest
import torch

from nsd.core.errors import FootageError
from nsd.io.footage import MultiViewFootage
from nsd.io.frame_store import FrameStore


def test_store_holds_the_decoded_frames_and_is_reused(tiny_scene):
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12))
    store = FrameStore(footage, footage.num_frames)
    frames = np.stack([v for _, v in footage.iter_frames()])  # (T, V, H, W, 3)
    assert store.shape == (4, 2, 3, 12, 16) and len(store) == 4
    assert torch.equal(store[2], torch.from_numpy(frames[2]).permute(0, 3, 1, 2))
    t, v = torch.tensor([3, 0, 3]), torch.tensor([1, 0, 0])
    assert torch.equal(store[t, v], torch.from_numpy(frames[[3, 0, 3], [1, 0, 0]]).permute(
        0, 3, 1, 2))
    assert torch.equal(store[1:3], torch.from_numpy(frames[1:3]).permute(0, 1, 4, 2, 3))
    view = store[2]  # basic indexing: a copy, writable, without torch's warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        store[0]
    view.zero_()
    assert torch.equal(store[2], torch.from_numpy(frames[2]).permute(0, 3, 1, 2))  # file intact
    stamp = store.path.stat().st_mtime_ns
    again = FrameStore(footage, footage.num_frames)  # the same footage: not decoded again
    assert again.path == store.path and again.path.stat().st_mtime_ns == stamp
    other = FrameStore(MultiViewFootage(tiny_scene, image_size=(8, 6)), 4)  # another size
    assert other.path != store.path and other.shape[-2:] == (6, 8)


def test_an_interrupted_decode_is_not_taken_for_a_store(tiny_scene):
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12))
    store = FrameStore(footage, 4)
    store.path.with_suffix(".json").unlink()  # as if the decode had been cut short
    with open(store.path, "r+b") as f:
        f.write(b"\xff" * 64)
    fresh = FrameStore(footage, 4)
    frames = np.stack([v for _, v in footage.iter_frames()])
    assert torch.equal(fresh[0], torch.from_numpy(frames[0]).permute(0, 3, 1, 2))


def test_an_unwritable_cache_keeps_frames_in_memory(tiny_scene, tmp_path, caplog):
    blocked = tmp_path / "a-file"  # the cache folder cannot be made (even by root)
    blocked.write_text("")
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12), cache_dir=blocked)
    with caplog.at_level(logging.WARNING):
        store = FrameStore(footage, 4)
    assert "held in memory" in caplog.text and store.shape == (4, 2, 3, 12, 16)
    frames = np.stack([v for _, v in footage.iter_frames()])
    assert torch.equal(store[3], torch.from_numpy(frames[3]).permute(0, 3, 1, 2))


def test_a_frame_stride_keeps_every_kth_frame(tiny_scene):
    """SceneData with frame_stride=2 holds footage frames 0 and 2 at positions 0 and 1,
    and its ground-truth lookups go through frame_index."""
    from nsd.io.scene_data import SceneData

    data = SceneData(tiny_scene, (16, 12), val_fraction=0.0, frame_stride=2)
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12))
    frames = np.stack([v for _, v in footage.iter_frames()])
    assert len(data.frames) == 2 and [data.frame_index(t) for t in (0, 1)] == [0, 2]
    assert torch.equal(data.frames[1], torch.from_numpy(frames[2]).permute(0, 3, 1, 2))
    assert list(data.train_frames) == [0, 1]


def test_streamed_and_in_memory_training_draw_the_same_batches(tiny_scene, tmp_path):
    """The frames behind a memory map (the default) and held in the process (an unwritable
    cache) give bit-identical training batches for the same seed."""
    from nsd.io.scene_data import SceneData

    streamed = SceneData(tiny_scene, (16, 12), val_fraction=0.0)
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    in_memory = SceneData(tiny_scene, (16, 12), val_fraction=0.0)
    in_memory.footage.cache_dir = blocked  # as an unwritable scene folder
    in_memory.frames = FrameStore(in_memory.footage, len(streamed.frames))
    assert isinstance(streamed.frames._array, np.memmap)
    assert not isinstance(in_memory.frames._array, np.memmap)  # held in the process
    a = streamed.sample(np.random.default_rng(7), 6)
    b = in_memory.sample(np.random.default_rng(7), 6)
    for name in ("image_v", "image_w", "background_v", "frame", "view_v", "view_w"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def _mapped_file(address: int) -> str:
    """The file behind the mapping holding ``address`` ('' for anonymous memory)."""
    for line in open("/proc/self/maps"):
        parts = line.split(maxsplit=5)
        lo, hi = (int(x, 16) for x in parts[0].split("-"))
        if lo <= address < hi:
            return parts[5].strip() if len(parts) > 5 else ""
    return ""


def test_scratch_array_is_a_zeroed_file_map_or_memory(tmp_path, caplog):
    from nsd.io.frame_store import scratch_array

    a = scratch_array(tmp_path / "frames", (3, 2, 4), np.int8)
    assert isinstance(a, np.memmap) and a.shape == (3, 2, 4) and not a.any()
    a[1] = -1
    assert a.sum() == -8
    assert list((tmp_path / "frames").iterdir()) == []  # an unnamed file: nothing left behind
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    with caplog.at_level(logging.WARNING):
        b = scratch_array(blocked / "frames", (2, 2), np.int8)
    assert not isinstance(b, np.memmap) and b.shape == (2, 2) and "held in memory" in caplog.text


def test_hull_owners_live_on_disk_and_equal_the_per_frame_hull(tiny_scene, tmp_path):
    """SceneData's (T, V, H, W) hull owners sit in a file map (memory flat in frames) and
    hold what the hull gives frame by frame (the reference), also when held in memory."""
    from nsd.cues.evidence import foreground_evidence
    from nsd.cues.occupancy import multiview_proposals, voxel_grid
    from nsd.io.scene_data import SceneData, to_float

    data = SceneData(tiny_scene, (16, 12), val_fraction=0.0)
    data.compute_multiview_proposals(2, 0.04, 0.04, resolution=12)
    assert data.owners.dtype == torch.int8 and "frames" in _mapped_file(data.owners.data_ptr())
    assert data.owners.shape == (4, 2, 12, 16)
    grid = voxel_grid(data.rig, data.frame_hw, 12)
    for t in range(4):
        ev = foreground_evidence(to_float(data.frames[t]), data.backgrounds, 0.04, 0.04)
        own = multiview_proposals(ev, grid, 2, split=True).owners
        assert torch.equal(data.owners[t], own.to(torch.int8)), t
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    kept = data.owners.clone()
    data.footage.cache_dir = blocked
    data.compute_multiview_proposals(2, 0.04, 0.04, resolution=12)
    assert torch.equal(data.owners, kept)


def test_cameras_decoded_side_by_side_give_the_file_decoded_one_by_one(tiny_scene, tmp_path):
    """Two processes (a camera each) write the same bytes as this process alone, also with a
    frame stride; the file holds camera v's frames in its slice [:, v]."""
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12))
    frames = np.stack([v for _, v in footage.iter_frames()])  # (T, V, H, W, 3)
    for stride in (1, 3):
        alone = FrameStore(footage, 4, stride, workers=1)
        together = FrameStore(MultiViewFootage(tiny_scene, image_size=(16, 12),
                                               cache_dir=tmp_path / f"c{stride}"),
                              4, stride, workers=2)
        assert alone.path.read_bytes() == together.path.read_bytes()
        assert np.array_equal(np.asarray(together._array), frames[::stride])
    assert not list(footage.cache_dir.glob("frames/.*.tmp"))


def test_a_camera_that_fails_to_decode_names_its_file_and_leaves_no_store(tiny_scene):
    """A frame that cannot be read in the second camera, decoded by a worker process: the
    error names the camera, file and frame; neither the store nor its record is left."""
    (tiny_scene / "right" / "000002.png").write_bytes(b"not a png")
    footage = MultiViewFootage(tiny_scene, image_size=(16, 12))
    with pytest.raises(FootageError, match=r"camera 'right'.*000002\.png, frame 2"):
        FrameStore(footage, 4, workers=2)
    left = list((footage.cache_dir / "frames").iterdir())
    assert left == [], left
