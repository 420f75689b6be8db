"""Videos of variable frame rate: OpenCV's seek is not frame-exact in them, so they are read
in order, and frame t is the t-th decoded frame whichever way it is asked.

The videos are written with PyAV (a test dependency: OpenCV cannot give frames their own
times), H.264 with B-frames as camera software writes it.
"""

from __future__ import annotations

import logging
import shutil
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from nsd.io.frame_sources import ImageFolderSource, VideoSource
from nsd.io.scene_check import check_scene

N = 120


BITS = 7  # 2**7 > N


def _image(t: int) -> np.ndarray:
    """Frame t: its number in binary, one black or white band of 8 pixels per bit, (48, 64, 3)."""
    img = np.zeros((48, 64, 3), np.uint8)
    for bit in range(BITS):
        img[:, 8 * bit:8 * bit + 8] = 255 * ((t >> bit) & 1)
    return img


def _which(frame: np.ndarray) -> int:
    """The number a decoded frame shows (each band's centre read against mid-grey)."""
    return sum(1 << bit for bit in range(BITS) if frame[:, 8 * bit + 2:8 * bit + 6].mean() > 128)


def _write(path: Path, times_ms: np.ndarray, images: list[np.ndarray] | None = None) -> Path:
    """An H.264 video, frame t showing ``images[t]`` (default: the number t, (48, 64, 3))
    at ``times_ms[t]``."""
    images = images or [_image(t) for t in range(len(times_ms))]
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=25)
        stream.height, stream.width = images[0].shape[:2]
        stream.pix_fmt, stream.options = "yuv420p", {"bf": "2", "g": "12"}
        stream.codec_context.time_base = Fraction(1, 1000)
        for img, ms in zip(images, times_ms, strict=True):
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = int(ms), Fraction(1, 1000)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def _opencv_seek(path: Path, t: int) -> int:
    cap = cv2.VideoCapture(str(path))
    cap.set(cv2.CAP_PROP_POS_FRAMES, t)
    ok, frame = cap.read()
    cap.release()
    return _which(frame) if ok else -1


JITTERED = np.cumsum(np.random.default_rng(1).integers(30, 50, N)) - 30
DROPPED = np.r_[np.arange(60), np.arange(61, N + 1)] * 40.0  # frame 60's time is missing
ASKED = [0, 3, 45, 59, 60, 61, 90, 118, N - 1]


def _read_exactly_with_a_warning(path: Path, caplog, why: str) -> None:
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert not src.seekable
    assert "camera 'side'" in caplog.text and str(path) in caplog.text
    assert "variable frame rate" in caplog.text and why in caplog.text
    assert src.num_frames == N
    assert [_which(src.read(t)) for t in ASKED] == ASKED
    assert [_which(f) for f in src.iter_frames([3, 3, 61, 118])] == [3, 3, 61, 118]
    assert [_which(f) for f in src.iter_range(57, 64)] == list(range(57, 64))


@pytest.mark.parametrize("ext", [".mp4", ".mkv"])
def test_a_video_of_jittered_frame_times_is_read_frame_exactly_with_a_warning(
        tmp_path, caplog, ext):
    path = _write(tmp_path / f"cam{ext}", JITTERED)
    # the case is real: OpenCV's own seek lands on another frame somewhere
    assert any(_opencv_seek(path, t) != t for t in ASKED)
    _read_exactly_with_a_warning(path, caplog, "are 30-49 ms apart")


def test_a_dropped_frame_after_the_probed_start_is_found_at_the_last_frame(tmp_path, caplog):
    """Even times over the first frames, one frame time missing later: the last frame is
    not where a constant rate puts it. (In a container without a frame count, mkv, OpenCV
    counts a frame for the gap and lands on the last frame for it: not found there.)"""
    _read_exactly_with_a_warning(_write(tmp_path / "cam.mp4", DROPPED), caplog,
                                 "not at 4760 ms")


@pytest.mark.parametrize("times", [np.arange(N) * 40.0,
                                   np.round(np.arange(N) * 1001 / 30)],  # 29.97 fps, in ms
                         ids=["25 fps", "29.97 fps rounded to ms"])
def test_a_constant_frame_rate_video_seeks_without_a_warning(tmp_path, caplog, times):
    path = _write(tmp_path / "cam.mp4", times)
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert src.seekable and caplog.text == ""
    assert src.num_frames == N
    asked = [0, 3, 45, 60, 118, N - 1]
    assert [_which(src.read(t)) for t in asked] == asked
    assert [_which(f) for f in src.iter_range(57, 64)] == list(range(57, 64))


def test_frames_asked_out_of_order_are_refused(tmp_path):
    src = VideoSource("side", _write(tmp_path / "cam.mp4", JITTERED))
    with pytest.raises(ValueError, match="increasing order"):
        list(src.iter_frames([5, 2]))
    with pytest.raises(Exception, match=r"camera 'side'.*frame 200"):
        list(src.iter_frames([2, 200]))


def test_the_scene_check_lists_a_camera_of_variable_frame_rate(tiny_scene):
    left = ImageFolderSource("left", tiny_scene / "left")
    images = [left.read(t) for t in range(left.num_frames)]
    shutil.rmtree(tiny_scene / "left")
    _write(tiny_scene / "left.mp4", np.array([0.0, 30.0, 75.0, 108.0]), images)
    w = check_scene(tiny_scene).warnings
    assert [x for x in w if "variable frame rate" in x] == [
        next(x for x in w if x.startswith(f"camera 'left' ({tiny_scene / 'left.mp4'})"))]
