"""The camera-rig type: intrinsics, distortion, pose and image size of static cameras.

One :class:`Camera` per view and a :class:`CameraRig` holding them in order. The
maths (projection, distortion) lives in :mod:`nsd.cameras.projection`; this module holds
the parameters, checks that they describe a physical camera, and offers the
numpy-facing conveniences (projection, unprojection, undistortion with OpenCV).
File formats are read and written by :mod:`nsd.cameras.calibration_io`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from nsd.cameras.batch import CameraBatch
from nsd.cameras.projection import (
    LENS_SIZE,
    SUPPORTED_DISTORTION_SIZES,
    fisheye_lens,
    pixel_to_normalized,
    project_points,
    relative_rotation,
)
from nsd.core.errors import CalibrationError

__all__ = ["Camera", "CameraRig"]

ORTHONORMAL_TOL = 1e-5  # |R R^T - I|_max above which a rotation is rejected
SINGULAR_TOL = 1e-9  # |det K| / (fx fy) below which K is rejected as singular


@dataclass(frozen=True, eq=False)
class Camera:
    """One static, calibrated camera (OpenCV conventions, see :mod:`nsd.cameras.projection`).

    Attributes:
        name: camera name, used to find its footage (``<scene>/<name>.*``).
        K: intrinsics, (3, 3) float64.
        dist: distortion (k1, k2, p1, p2[, k3[, k4, k5, k6]]), (n,) float64.
        R: world-to-camera rotation, (3, 3) float64.
        t: world-to-camera translation, (3,) float64, in scene units (metres for
            scenes written by this toolkit).
        size: image size ``(width, height)`` in pixels, or None when the file
            does not store it (it is then taken from the footage).
        fisheye: Kannala-Brandt lens (``cv2.fisheye``): ``dist`` holds k1..k4.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int] | None = None
    source: str = field(default="", compare=False)
    fisheye: bool = False

    def __post_init__(self) -> None:
        for attr, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,))):
            value = np.asarray(getattr(self, attr), dtype=np.float64)
            if value.shape != shape:
                value = value.reshape(-1)
                if value.size != int(np.prod(shape)):
                    raise CalibrationError(
                        f"{self._where()}: {attr} has {value.size} values, expected shape {shape}"
                    )
                value = value.reshape(shape)
            object.__setattr__(self, attr, value)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        object.__setattr__(self, "dist", dist)
        if self.size is not None:
            object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))
        self.validate()

    def _where(self) -> str:
        return f"camera '{self.name}'" + (f" in {self.source}" if self.source else "")

    def validate(self) -> None:
        """Raise :class:`CalibrationError` unless this is a physically valid camera.

        Checks: finite values; K upper-triangular with positive focal lengths and
        non-singular; R orthonormal with determinant +1; a supported number of
        distortion coefficients; a positive image size.
        """
        where = self._where()
        for attr in ("K", "dist", "R", "t"):
            if not np.all(np.isfinite(getattr(self, attr))):
                raise CalibrationError(f"{where}: {attr} has non-finite values")
        K = self.K
        if abs(K[1, 0]) > 0 or abs(K[2, 0]) > 0 or abs(K[2, 1]) > 0 or K[2, 2] != 1.0:
            raise CalibrationError(f"{where}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        if (
            K[0, 0] <= 0
            or K[1, 1] <= 0
            or abs(np.linalg.det(K)) < SINGULAR_TOL * max(1.0, abs(K[0, 0] * K[1, 1]))
        ):
            raise CalibrationError(
                f"{where}: K is singular (fx={K[0, 0]}, fy={K[1, 1]}); focal lengths must be > 0"
            )
        err = np.abs(self.R @ self.R.T - np.eye(3)).max()
        if err > ORTHONORMAL_TOL or np.linalg.det(self.R) < 0:
            raise CalibrationError(
                f"{where}: rotation is not orthonormal with det +1 "
                f"(max |R R^T - I| = {err:.2e}, det = {np.linalg.det(self.R):.4f})"
            )
        if self.fisheye and self.dist.size != 4:
            raise CalibrationError(
                f"{where}: a fisheye (Kannala-Brandt) lens has 4 coefficients k1..k4, "
                f"got {self.dist.size}")
        if self.dist.size not in SUPPORTED_DISTORTION_SIZES:
            raise CalibrationError(
                f"{where}: {self.dist.size} distortion coefficients; "
                f"supported: {SUPPORTED_DISTORTION_SIZES}"
            )
        if self.size is not None and (self.size[0] <= 0 or self.size[1] <= 0):
            raise CalibrationError(f"{where}: image size {self.size} must be positive")

    # ------------------------------------------------------------------ geometry
    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates, (3,): ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def viewing_direction(self) -> np.ndarray:
        """Unit optical axis in world coordinates, (3,): ``R^T (0, 0, 1)``."""
        return self.R[2].copy()

    def tensors(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> dict[str, torch.Tensor]:
        """This one camera's K (3, 3), R (3, 3), t (3,), dist (n,) as unbatched tensors.

        A batch of cameras: :meth:`CameraRig.stacked` (a :class:`CameraBatch`).
        """
        out = {
            k: torch.as_tensor(getattr(self, k), dtype=dtype, device=device)
            for k in ("K", "R", "t", "dist")
        }
        if self.fisheye:
            out["dist"] = fisheye_lens(out["dist"])
        return out

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) to pixels (N, 2); also returns depth (N,)."""
        p = self.tensors(torch.float64)
        uv, z = project_points(torch.as_tensor(np.asarray(points, np.float64)), **p)
        return uv.numpy(), z.numpy()

    def unproject(self, uv: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """Pixels (N, 2) to world rays or points.

        Returns:
            With ``depth`` (N,) (camera-space Z): world points (N, 3). Without:
            unit ray directions in world coordinates (N, 3); rays start at
            :attr:`center`.
        """
        p = self.tensors(torch.float64)
        xy = pixel_to_normalized(torch.as_tensor(np.asarray(uv, np.float64)), p["K"], p["dist"])
        d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1).numpy()
        if depth is not None:
            return (d_cam * np.asarray(depth, np.float64)[:, None] - self.t) @ self.R
        d_world = d_cam @ self.R
        return d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)

    def undistort_image(self, image: np.ndarray) -> np.ndarray:
        """Remove lens distortion from an image of this camera (OpenCV, same K)."""
        if not np.any(self.dist):
            return image.copy()
        if self.fisheye:
            return cv2.fisheye.undistortImage(image, self.K, self.dist, Knew=self.K)
        return cv2.undistort(image, self.K, self.dist)

    def scaled(self, size: tuple[int, int]) -> Camera:
        """The same camera for images resized to ``size`` = (width, height).

        Pixel centres map as ``u' = (u + 0.5) * sx - 0.5``, which is what
        ``cv2.resize`` does.
        """
        if self.size is None:
            raise CalibrationError(f"{self._where()}: cannot rescale a camera without image size")
        sx, sy = size[0] / self.size[0], size[1] / self.size[1]
        S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
        return dataclasses.replace(self, K=S @ self.K, size=(int(size[0]), int(size[1])))

    def with_size(self, size: tuple[int, int]) -> Camera:
        """This camera with its image size set (for formats that do not store it)."""
        return dataclasses.replace(self, size=(int(size[0]), int(size[1])))

    def equals(self, other: Camera, atol: float = 0.0) -> bool:
        """Same name, size and parameters (within ``atol``)."""
        return (
            self.name == other.name
            and self.size == other.size
            and self.fisheye == other.fisheye
            and self.dist.shape == other.dist.shape
            and all(
                np.allclose(getattr(self, a), getattr(other, a), rtol=0, atol=atol)
                for a in ("K", "dist", "R", "t")
            )
        )


class CameraRig(Sequence[Camera]):
    """An ordered set of cameras with unique names.

    Index by position or by name. ``rig.relative_rotation(v, w)`` is
    :math:`R_{v \\to w} = R_w R_v^T` (see :func:`nsd.cameras.projection.relative_rotation`).
    """

    def __init__(self, cameras: Sequence[Camera], source: str = "") -> None:
        self._cameras = list(cameras)
        self.source = source
        self.units_note = ""  # set by nsd.cameras.units.in_metres when it inferred the unit
        if not self._cameras:
            raise CalibrationError(f"{source or 'calibration'}: no cameras")
        names = [c.name for c in self._cameras]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CalibrationError(f"{source or 'calibration'}: duplicate camera names {dupes}")

    def __len__(self) -> int:
        return len(self._cameras)

    def __getitem__(self, key):  # type: ignore[override]
        if isinstance(key, str):
            for c in self._cameras:
                if c.name == key:
                    return c
            raise KeyError(f"no camera named '{key}' (cameras: {self.names})")
        if isinstance(key, slice):
            return CameraRig(self._cameras[key], self.source)
        return self._cameras[key]

    def __iter__(self) -> Iterator[Camera]:
        return iter(self._cameras)

    def __repr__(self) -> str:
        return f"CameraRig({self.names}, source={self.source!r})"

    @property
    def names(self) -> list[str]:
        return [c.name for c in self._cameras]

    def index(self, name: str) -> int:  # type: ignore[override]
        return self.names.index(name)

    def select(self, names: Sequence[str]) -> CameraRig:
        """The cameras ``names`` in that order."""
        return CameraRig([self[n] for n in names], self.source)

    def relative_rotation(self, v: int | str, w: int | str) -> np.ndarray:
        """:math:`R_{v \\to w}`, (3, 3)."""
        Rv, Rw = torch.as_tensor(self[v].R), torch.as_tensor(self[w].R)
        return relative_rotation(Rv, Rw).numpy()

    def stacked(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> CameraBatch:
        """The rig as a :class:`CameraBatch` of V cameras, for batched projection.

        Distortion vectors are zero-padded to the longest in the rig; a rig with a fisheye
        camera gets lens vectors (:data:`nsd.cameras.projection.LENS_SIZE` entries).
        """
        n = max(c.dist.size for c in self._cameras)
        n = next(s for s in SUPPORTED_DISTORTION_SIZES if s >= n)
        if any(c.fisheye for c in self._cameras):
            n = LENS_SIZE
        dist = np.zeros((len(self), n))
        for i, c in enumerate(self._cameras):
            dist[i, : c.dist.size] = c.dist
            if c.fisheye:
                dist[i, -1] = 1.0
        K, R, t = (
            torch.as_tensor(np.stack([getattr(c, k) for c in self._cameras]), dtype=dtype)
            for k in ("K", "R", "t")
        )
        return CameraBatch(K, R, t, torch.as_tensor(dist, dtype=dtype)).to(device)

    def with_translation_scale(self, factor: float) -> CameraRig:
        """The rig with every translation times ``factor`` (a change of length unit)."""
        return CameraRig([dataclasses.replace(c, t=c.t * factor) for c in self], self.source)

    def scaled(self, size: tuple[int, int]) -> CameraRig:
        """Every camera rescaled to images of ``size`` = (width, height)."""
        return CameraRig([c.scaled(size) for c in self._cameras], self.source)

    def equals(self, other: CameraRig, atol: float = 0.0) -> bool:
        return len(self) == len(other) and all(
            a.equals(b, atol) for a, b in zip(self, other, strict=True)
        )
