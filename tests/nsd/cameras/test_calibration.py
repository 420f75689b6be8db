"""The camera type: validation, geometry helpers, rescaling."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from nsd.cameras.calibration import Camera, CameraRig
from nsd.core.errors import CalibrationError
from tests.conftest import look_at_camera


@pytest.fixture
def cam() -> Camera:
    return look_at_camera(
        "c", np.array([4.0, 1.0, 2.0]), dist=np.array([-0.1, 0.02, 0.0, 0.0, 0.0])
    )


def _replace(cam: Camera, **kw) -> Camera:
    fields = {f.name: getattr(cam, f.name) for f in dataclasses.fields(cam)}
    fields.update(kw)
    return Camera(**fields)


class TestValidation:
    @pytest.mark.parametrize("attr", ["K", "R", "t", "dist"])
    def test_non_finite(self, cam, attr):
        bad = np.array(getattr(cam, attr), dtype=float)
        bad.flat[0] = np.nan
        with pytest.raises(CalibrationError, match=rf"camera 'c'.*{attr} has non-finite"):
            _replace(cam, **{attr: bad})

    def test_singular_K(self, cam):
        K = cam.K.copy()
        K[1, 1] = 0.0
        with pytest.raises(CalibrationError, match="K is singular"):
            _replace(cam, K=K)

    def test_non_orthonormal_rotation(self, cam):
        with pytest.raises(CalibrationError, match="not orthonormal"):
            _replace(cam, R=cam.R * 1.01)

    def test_reflection_rejected(self, cam):
        with pytest.raises(CalibrationError, match="det"):
            _replace(cam, R=cam.R * np.array([[1], [1], [-1]]))

    def test_distortion_size(self, cam):
        with pytest.raises(CalibrationError, match="3 distortion coefficients"):
            _replace(cam, dist=np.zeros(3))

    def test_bad_size(self, cam):
        with pytest.raises(CalibrationError, match="image size"):
            _replace(cam, size=(0, 10))

    def test_wrong_shape(self, cam):
        with pytest.raises(CalibrationError, match="t has 2 values"):
            _replace(cam, t=np.zeros(2))

    def test_source_is_named(self, cam):
        with pytest.raises(CalibrationError, match=r"camera 'c' in /some/calib.toml"):
            _replace(cam, K=np.zeros((3, 3)), source="/some/calib.toml")

    def test_duplicate_names(self, cam):
        with pytest.raises(CalibrationError, match="duplicate camera names"):
            CameraRig([cam, cam])


class TestGeometry:
    def test_center_and_direction(self, cam):
        np.testing.assert_allclose(cam.center, [4.0, 1.0, 2.0], atol=1e-12)
        d = -np.array([4.0, 1.0, 2.0]) / np.linalg.norm([4.0, 1.0, 2.0])
        np.testing.assert_allclose(cam.viewing_direction, d, atol=1e-12)
        # the principal point of an undistorted camera sees the target
        uv, _ = look_at_camera("u", np.array([4.0, 1.0, 2.0])).project(np.zeros((1, 3)))
        np.testing.assert_allclose(uv, [[159.5, 119.5]], atol=1e-9)

    def test_scaled_matches_cv2_resize(self, cam):
        """A point drawn at its projection stays at the scaled projection after cv2.resize."""
        small = cam.scaled((160, 120))
        X = np.array([[0.3, -0.2, 0.4]])
        uv, _ = cam.project(X)
        uv_s, _ = small.project(X)
        img = np.zeros((240, 320), np.float32)
        u, v = np.round(uv[0]).astype(int)
        img[v - 4 : v + 6, u - 4 : u + 6] = 1.0  # 10x10 block centred at (u + 0.5, v + 0.5)
        res = cv2.resize(img, (160, 120), interpolation=cv2.INTER_AREA)
        ys, xs = np.nonzero(res > 0)
        w = res[ys, xs]
        centroid = np.array([(xs * w).sum(), (ys * w).sum()]) / w.sum()
        expected = small.project(X)[0][0] + (np.array([u, v]) + 0.5 - uv[0]) / 2
        np.testing.assert_allclose(centroid, expected, atol=1e-6)
        assert small.size == (160, 120)
        np.testing.assert_allclose(uv_s, (uv + 0.5) / 2 - 0.5, atol=1e-9)

    def test_rig_indexing_and_relative_rotation(self, random_cameras):
        rig = CameraRig(random_cameras)
        assert rig["cam2"] is random_cameras[2]
        assert rig.index("cam4") == 4
        R = rig.relative_rotation("cam0", 3)
        np.testing.assert_allclose(R, random_cameras[3].R @ random_cameras[0].R.T, atol=1e-12)
        with pytest.raises(KeyError, match="no camera named 'nope'"):
            rig["nope"]
        stacked = rig.stacked()
        assert stacked.K.shape == (6, 3, 3) and stacked.dist.shape == (6, 8)

    def test_undistort_image_straightens_lines(self):
        """A straight world line imaged through a distorting lens is straight after undistortion."""
        cam = look_at_camera(
            "d", np.array([0.0, -3.0, 0.0]), f=200, dist=np.array([-0.35, 0.1, 0.0, 0.0, 0.0])
        )
        pts = np.stack([np.linspace(-1.5, 1.5, 400), np.zeros(400), np.full(400, 1.3)], 1)
        uv, _ = cam.project(pts)
        img = np.zeros((240, 320), np.uint8)
        for u, v in np.round(uv).astype(int):
            if 0 <= u < 320 and 0 <= v < 240:
                img[v, u] = 255
        ys_d, _ = np.nonzero(img)
        und = cam.undistort_image(img)
        ys, _ = np.nonzero(und > 60)
        assert np.ptp(ys_d) >= 5  # visibly curved before
        assert np.ptp(ys) <= 2  # straight (within pixel rounding) after
