"""Videos of variable frame rate: OpenCV's seek is not frame-exact in them, so they are read
in order, and frame t is the t-th decoded frame whichever way it is asked. Videos of a
constant rate whose camera dropped frames: frame t is the instant t, a dropped one filled
with the frame before it, so that the camera stays in step with the others.

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


def _write(path: Path, times_ms: np.ndarray, images: list[np.ndarray] | None = None,
           rate: float = 25) -> Path:
    """An H.264 video, frame t showing ``images[t]`` (default: the number t, (48, 64, 3))
    at ``times_ms[t]``, declaring ``rate`` frames per second."""
    images = images or [_image(t) for t in range(len(times_ms))]
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=Fraction(rate).limit_denominator(1001))
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


@pytest.mark.parametrize("ext", [".mp4", ".mkv"])
@pytest.mark.parametrize("missing", [[60], [10, 75, 76]],
                         ids=["one after the probed start", "three, one in the probe"])
def test_frames_the_camera_dropped_are_filled_so_that_it_stays_in_step(
        tmp_path, caplog, ext, missing):
    """Frames every 40 ms, some instants without one. Frame t shows instant t (or, where the
    camera dropped it, the instant before), whichever way it is asked. Before: the mp4 was
    read as variable frame rate of 117-119 frames (out of step after the drop), and the mkv
    (no frame count in the container) was counted 120 with no warning and stopped at the
    missing last frame when read in order."""
    instants = [s for s in range(N) if s not in missing]
    path = _write(tmp_path / f"cam{ext}", np.array(instants) * 40.0,
                  [_image(s) for s in instants])
    held = [max(s for s in instants if s <= t) for t in range(N)]
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert not src.seekable
    assert src.num_frames == N
    assert [_which(src.read(t)) for t in ASKED] == [held[t] for t in ASKED]
    assert [_which(f) for f in src.iter_range(0, N)] == held
    assert [_which(f) for f in src.iter_frames([3, 3, 61, 118])] == [held[t] for t in
                                                                       [3, 3, 61, 118]]
    text = caplog.text
    assert "camera 'side'" in text and str(path) in text and "variable frame rate" not in text
    shown = ", ".join(f"{m} ({m * 40} ms)" for m in missing)
    assert (f"{len(missing)} frame(s) missing from its timeline of one frame every 40.0 ms: "
            f"frame(s) {shown} (the camera dropped them)") in text


def test_a_frame_that_is_late_but_not_dropped_is_variable_frame_rate(tmp_path, caplog):
    """One frame time 20 ms late (half a frame) after the probed start: not a whole instant
    missing, so the video is read as variable frame rate, frame t the t-th frame."""
    times = np.arange(N) * 40.0
    times[70] += 20
    path = _write(tmp_path / "cam.mkv", times)
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert not src.seekable and src.num_frames == N
    assert "variable frame rate (its frames are 20-60 ms apart)" in caplog.text
    assert [_which(f) for f in src.iter_range(66, 74)] == list(range(66, 74))


@pytest.mark.parametrize("ext", [".mp4", ".mkv"])
@pytest.mark.parametrize("times", [np.arange(N) * 40.0,
                                   np.round(np.arange(N) * 1001 / 30)],  # 29.97 fps, in ms
                         ids=["25 fps", "29.97 fps rounded to ms"])
def test_a_constant_frame_rate_video_seeks_without_a_warning(tmp_path, caplog, times, ext):
    path = _write(tmp_path / f"cam{ext}", times, rate=round(1000 / np.diff(times).mean(), 2))
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert src.seekable and caplog.text == ""
    assert src.num_frames == N
    asked = [0, 3, 45, 60, 118, N - 1]
    assert [_which(src.read(t)) for t in asked] == asked
    assert [_which(f) for f in src.iter_range(57, 64)] == list(range(57, 64))


def test_an_mkv_declaring_another_rate_than_its_frames_is_read_in_order(tmp_path, caplog):
    """Frames every 33.4 ms in an mkv that declares 25 fps: OpenCV counts 100 frames and its
    seek, which goes by the declared rate, lands on other frames; all 120 are read exactly."""
    times = np.round(np.arange(N) * 1001 / 30)
    path = _write(tmp_path / "cam.mkv", times)
    assert _opencv_seek(path, 45) != 45  # the case is real
    with caplog.at_level(logging.WARNING, logger="nsd.io.frame_sources"):
        src = VideoSource("side", path)
    assert not src.seekable and src.num_frames == N
    assert (f"OpenCV's seek is not frame-exact in it: a seek to its last frame, {N - 1}, "
            f"lands") in caplog.text and "the file declares 25.000 fps" in caplog.text
    assert [_which(src.read(t)) for t in ASKED] == ASKED
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
