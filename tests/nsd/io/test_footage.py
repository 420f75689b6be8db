"""Multi-view footage: synchronised frames, view pairs, median backgrounds, bad input."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from nsd.cameras.calibration_io import read_toml, write_toml
from nsd.core.errors import CalibrationError, FootageError
from nsd.io.footage import MAX_FRAME_TRIM, MultiViewFootage
from nsd.io.frame_sources import VideoSource
from tests.conftest import write_video


def _moving_object_frames(n: int, h: int = 24, w: int = 32, seed: int = 0) -> tuple:
    """A static textured background with a square crossing it: (frames, background)."""
    rng = np.random.default_rng(seed)
    bg = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    bg = cv2.GaussianBlur(bg, (5, 5), 0)
    frames = np.repeat(bg[None], n, axis=0)
    for t in range(n):
        x = round((w - 6) * t / max(1, n - 1))
        y = (t * 5) % (h - 6)
        frames[t, y : y + 6, x : x + 6] = (255, 20, 20)
    return frames, bg


def _as_video_scene(scene: Path, n: int = 60) -> np.ndarray:
    """Replace the fixture's image folders by .avi videos of a moving square."""
    bgs = []
    for v, name in enumerate(["left", "right"]):
        shutil.rmtree(scene / name)
        frames, bg = _moving_object_frames(n, seed=v)
        write_video(scene / f"{name}.avi", frames)
        bgs.append(bg)
    return np.stack(bgs)


class TestReading:
    def test_fixture_frames(self, tiny_scene):
        f = MultiViewFootage(tiny_scene)
        assert f.num_frames == 4 and f.num_views == 2 and f.camera_names == ["left", "right"]
        views = f.frame(2)
        assert views.shape == (2, 24, 32, 3) and views.dtype == np.uint8
        expected = cv2.cvtColor(
            cv2.imread(str(tiny_scene / "right" / "000002.png")), cv2.COLOR_BGR2RGB
        )
        np.testing.assert_array_equal(views[1], expected)
        streamed = [v for _, v in f.iter_frames()]
        np.testing.assert_array_equal(np.stack(streamed), f.load())
        np.testing.assert_array_equal(streamed[2], views)

    def test_video_frames_are_synchronised(self, tiny_scene):
        _as_video_scene(tiny_scene, n=12)
        f = MultiViewFootage(tiny_scene)
        assert f.num_frames == 12
        # random access equals sequential decoding
        seq = f.load()
        for t in (0, 5, 11):
            np.testing.assert_array_equal(f.frame(t), seq[t])

    def test_resize_scales_intrinsics(self, tiny_scene):
        f = MultiViewFootage(tiny_scene, image_size=(16, 12))
        assert f.frame(0).shape == (2, 12, 16, 3)
        X = np.array([[0.1, 0.2, 0.3]])
        full, small = f.native_rig["left"], f.rig["left"]
        np.testing.assert_allclose(small.project(X)[0], (full.project(X)[0] + 0.5) / 2 - 0.5)

    def test_camera_subset(self, tiny_scene):
        f = MultiViewFootage(tiny_scene, cameras=["right"])
        assert f.camera_names == ["right"] and f.frame(0).shape[0] == 1
        with pytest.raises(FootageError, match=r"cameras \['top'\] are not in the calibration"):
            MultiViewFootage(tiny_scene, cameras=["top"])

    def test_view_pairs(self, tiny_scene):
        f = MultiViewFootage(tiny_scene)
        t, v, w = f.sample_view_pairs(np.random.default_rng(0), 500)
        assert (v != w).all() and set(v) == {0, 1} and set(w) == {0, 1}
        assert t.min() >= 0 and t.max() < 4 and len(set(t)) == 4


class TestBackground:
    def test_median_recovers_static_background_images(self, tiny_scene):
        """Lossless image folders: the median equals the background exactly."""
        for v, name in enumerate(["left", "right"]):
            shutil.rmtree(tiny_scene / name)
            (tiny_scene / name).mkdir()
            frames, bg = _moving_object_frames(30, seed=v)
            for t, img in enumerate(frames):
                cv2.imwrite(
                    str(tiny_scene / name / f"{t}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
                )
            if v == 0:
                bg0 = bg
        f = MultiViewFootage(tiny_scene)
        bgs = f.background()
        np.testing.assert_array_equal(bgs[0], bg0)
        assert (f.frame(3)[0] != bg0).any()  # the object is there in single frames

    def test_median_recovers_static_background_video_and_caches(self, tiny_scene):
        truth = _as_video_scene(tiny_scene, n=60)
        f = MultiViewFootage(tiny_scene)
        bgs = f.background()
        err = np.abs(bgs.astype(int) - truth.astype(int)).mean(-1)
        single = np.abs(f.frame(30).astype(int) - truth.astype(int)).mean(-1)
        square = single > 60  # where frame 30 shows the square
        codec_noise = single[~square].mean()
        assert square.sum() >= 30  # the square is visible in a single frame ...
        assert err[square].max() < 40  # ... but not in the median
        assert err.mean() < 1.5 * codec_noise + 1  # which is as close as the codec allows
        folder = tiny_scene / ".cache" / "background"

        def images(pattern):  # the backgrounds, without their uncertainty masks
            return [p for p in folder.glob(pattern) if not p.name.endswith(".uncertain.png")]

        assert len(images("*.png")) == 2
        assert len(list(folder.glob("*.uncertain.png"))) == 2
        # the cache is used: corrupting the videos' pixels is not noticed ...
        again = MultiViewFootage(tiny_scene).background()
        np.testing.assert_array_equal(again, bgs)
        # ... but changed footage is (new signature -> recomputed)
        frames, _ = _moving_object_frames(60, seed=5)
        write_video(tiny_scene / "left.avi", frames)
        MultiViewFootage(tiny_scene).background()
        assert len(images("left.*.png")) == 2


class TestBadInput:
    def test_missing_camera(self, tiny_scene):
        shutil.rmtree(tiny_scene / "right")
        with pytest.raises(FootageError, match=r"camera 'right': no video .*right.mp4"):
            MultiViewFootage(tiny_scene)

    def test_a_camera_one_frame_short_is_trimmed_with_a_warning(self, tiny_scene, caplog):
        (tiny_scene / "right" / "000003.png").unlink()
        with caplog.at_level(logging.WARNING):
            footage = MultiViewFootage(tiny_scene)
        assert footage.num_frames == 3 and footage.frame(2).shape[0] == 2
        assert re.search(r"different numbers of frames \('left' .*: 4, 'right' .*: 3\)",
                         caplog.text)

    def test_frame_counts_far_apart_are_an_error(self, tiny_scene):
        for t in range(4, 4 + MAX_FRAME_TRIM + 1):  # left: 4 + 11 frames, right: 4
            shutil.copy(tiny_scene / "left" / "000000.png", tiny_scene / "left" / f"{t:06d}.png")
        with pytest.raises(
            FootageError,
            match=r"different numbers of frames.*'left' \(.*left\): 15.*'right' \(.*right\): 4",
        ):
            MultiViewFootage(tiny_scene)

    def test_a_video_that_decodes_fewer_frames_than_claimed_uses_those(self, tiny_scene,
                                                                       caplog):
        """A truncated AVI still claims its 40 frames in its header; 24 decode."""
        shutil.rmtree(tiny_scene / "left")
        frames, _ = _moving_object_frames(40, seed=3)
        path = write_video(tiny_scene / "left.avi", frames)
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * 0.6)])
        with caplog.at_level(logging.WARNING):
            src = VideoSource("left", path)
        assert re.search(r"camera 'left' \(.*left.avi\): the container claims 40 frames but "
                         r"only \d+ decode", caplog.text)
        n = src.num_frames
        assert 0 < n < 40
        assert src.read(n - 1).shape == frames.shape[1:]  # the last frame used decodes
        assert len(list(src.iter_range(0, n))) == n

    def test_unreadable_video(self, tiny_scene):
        shutil.rmtree(tiny_scene / "left")
        (tiny_scene / "left.mp4").write_bytes(b"this is not a video" * 100)
        with pytest.raises(FootageError, match=r"camera 'left' \(.*left.mp4\)"):
            MultiViewFootage(tiny_scene)

    def test_zero_frame_video(self, tiny_scene):
        shutil.rmtree(tiny_scene / "left")
        write_video(tiny_scene / "left.avi", np.zeros((0, 24, 32, 3), np.uint8))
        with pytest.raises(
            FootageError, match=r"camera 'left' \(.*left.avi\).*(zero readable frames|cannot open)"
        ):
            MultiViewFootage(tiny_scene)

    def test_truncated_video_is_caught_when_the_footage_is_opened(self, tiny_scene):
        """Half of left.avi decodes: far fewer frames than right's 40, before any work."""
        _as_video_scene(tiny_scene, n=40)
        data = (tiny_scene / "left.avi").read_bytes()
        (tiny_scene / "left.avi").write_bytes(data[: len(data) // 2])
        with pytest.raises(FootageError, match=r"'left' \(.*left.avi\): \d+, 'right' .*: 40"):
            MultiViewFootage(tiny_scene)

    def test_unreadable_image_names_file_and_frame(self, tiny_scene):
        (tiny_scene / "left" / "000002.png").write_bytes(b"garbage")
        f = MultiViewFootage(tiny_scene)
        with pytest.raises(FootageError, match=r"camera 'left' \(.*000002.png, frame 2\)"):
            f.frame(2)

    def test_empty_image_folder(self, tiny_scene):
        for p in (tiny_scene / "left").iterdir():
            p.unlink()
        with pytest.raises(
            FootageError, match=r"camera 'left' \(.*left\): image folder holds no images"
        ):
            MultiViewFootage(tiny_scene)

    def test_size_disagrees_with_calibration(self, tiny_scene):
        rig = read_toml(tiny_scene / "calibration.toml")
        write_toml(rig.scaled((64, 48)), tiny_scene / "calibration.toml")
        with pytest.raises(CalibrationError, match=r"camera 'left'.*64x48 but .*left is 32x24"):
            MultiViewFootage(tiny_scene)

    def test_missing_scene(self, tmp_path):
        with pytest.raises(FootageError, match="does not exist"):
            MultiViewFootage(tmp_path / "nowhere")

    def test_frame_out_of_range(self, tiny_scene):
        with pytest.raises(FootageError, match="frame 9 out of range"):
            MultiViewFootage(tiny_scene).frame(9)


class TestBackgroundPlates:
    def test_a_plate_replaces_the_median(self, tiny_scene):
        plate = np.full((24, 32, 3), (10, 200, 30), np.uint8)  # RGB
        (tiny_scene / "background").mkdir()
        cv2.imwrite(str(tiny_scene / "background" / "left.png"), plate[..., ::-1])
        footage = MultiViewFootage(tiny_scene)
        bg = footage.background()
        np.testing.assert_array_equal(bg[0], plate)
        median = np.median(np.stack([footage.frame(t)[1] for t in range(4)]), axis=0)
        np.testing.assert_array_equal(bg[1], median.round().astype(np.uint8))  # no plate

    def test_a_plate_folder_gives_the_median_of_its_images(self, tiny_scene):
        (tiny_scene / "background" / "right").mkdir(parents=True)
        for i, v in enumerate((10, 50, 90)):
            cv2.imwrite(str(tiny_scene / "background" / "right" / f"{i}.png"),
                        np.full((24, 32, 3), v, np.uint8))
        assert (MultiViewFootage(tiny_scene).background()[1] == 50).all()

    def test_a_plate_of_another_size_is_named(self, tiny_scene):
        (tiny_scene / "background").mkdir()
        cv2.imwrite(str(tiny_scene / "background" / "left.jpg"), np.zeros((10, 10, 3), np.uint8))
        with pytest.raises(FootageError, match=r"camera 'left': background plate .*left.jpg is "
                                               r"10x10 but the footage is 32x24"):
            MultiViewFootage(tiny_scene).background()
