r"""11-parameter DLT calibrations (Argus, DLTdv, easyWand): read into and written from a rig.

A DLT camera maps a world point :math:`(X, Y, Z)` to image coordinates

.. math::
    u = \frac{L_1 X + L_2 Y + L_3 Z + L_4}{L_9 X + L_{10} Y + L_{11} Z + 1},\quad
    v = \frac{L_5 X + L_6 Y + L_7 Z + L_8}{L_9 X + L_{10} Y + L_{11} Z + 1},

a 3 x 4 projection matrix with its last entry 1: exactly a pinhole camera with skew and
no lens distortion (11 degrees of freedom), so the reader recovers K (with skew), R and t
by an RQ decomposition and loses nothing.

The file: comma-separated, 11 rows (L1..L11) and one column per camera, no header, as
Argus's ``*_dlt-coefs.csv``, DLTdv's and easyWand's coefficient files write it. Cameras
are named ``cam1``, ``cam2``, ... in column order (the file holds no names; name the
scene's footage the same). The image coordinates of these tools put the origin at the
*lower left*, y up, with MATLAB's 1-based pixel centres: ``u = x + 1``, ``v = H - y``
for OpenCV pixels ``(x, y)`` (centre of the top-left pixel at (0, 0)) of an image H pixels
high; so the image heights are needed, and are taken from the footage beside the file
(``origin="upper_left"`` reads coefficients of 0-based, y-down pixels, as some
Python tools fit them).
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from nsd.cameras.calibration import Camera, CameraRig
from nsd.core.atomic import atomic_write_text
from nsd.core.errors import CalibrationError

__all__ = ["DLT_ORIGINS", "dlt_from_camera", "read_dlt", "write_dlt"]

DLT_ORIGINS = ("lower_left", "upper_left")


def _to_ours(height: int, origin: str) -> np.ndarray:
    """3 x 3 map from the file's image coordinates to OpenCV pixels."""
    if origin == "upper_left":
        return np.eye(3)
    return np.array([[1.0, 0.0, -1.0], [0.0, -1.0, float(height)], [0.0, 0.0, 1.0]])


def _camera(name: str, coefs: np.ndarray, size: tuple[int, int], origin: str,
            source: Path) -> Camera:
    P = _to_ours(size[1], origin) @ np.append(coefs, 1.0).reshape(3, 4)
    if np.linalg.det(P[:, :3]) < 0:  # the projective scale's sign: det(K R) > 0
        P = -P
    K, R, _, _, _, _, _ = cv2.decomposeProjectionMatrix(P)
    signs = np.diag(np.sign(np.diag(K)))  # RQ leaves signs free: positive focal lengths
    K, R = K @ signs, signs @ R
    t = np.linalg.solve(K, P[:, 3])
    if t[2] <= 0:  # with det(K R) > 0 a mirrored world puts the scene behind the camera
        raise CalibrationError(
            f"camera '{name}' in {source}: the world origin lies behind the camera, so the DLT "
            "maps a left-handed (mirrored) world, or another image origin (origin="
            "upper_left / lower_left); recalibrate with a right-handed frame")
    K = K / K[2, 2]
    K[1, 0] = K[2, 0] = K[2, 1] = 0.0
    return Camera(name=name, K=K, dist=np.zeros(0), R=R, t=t, size=size, source=str(source))


def read_dlt(path: str | os.PathLike, sizes: dict[str, tuple[int, int]] | None = None,
             origin: str = "lower_left") -> CameraRig:
    """Read an 11-row DLT coefficient file (module docstring).

    Args:
        path: the ``.csv`` file.
        sizes: camera name -> image (width, height); default: from the footage of
            ``cam1``, ``cam2``, ... in the file's folder (or the folder above a
            ``calibration/`` folder).
        origin: the file's image origin, one of :data:`DLT_ORIGINS`.

    Raises:
        CalibrationError: not 11 numeric rows, no image size for a camera, a degenerate or
            mirrored camera.
    """
    path = Path(path)
    if origin not in DLT_ORIGINS:
        raise CalibrationError(f"DLT origin {origin!r}: one of {DLT_ORIGINS}")
    try:
        rows = [[float(v) for v in r if v.strip()] for r in csv.reader(io.StringIO(
            path.read_text())) if any(v.strip() for v in r)]
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise CalibrationError(f"{path}: not a DLT coefficient file (11 numeric rows): {e}") \
            from None
    if len(rows) != 11 or len({len(r) for r in rows}) != 1 or not rows[0]:
        raise CalibrationError(f"{path}: a DLT coefficient file has 11 rows of one value per "
                               f"camera; found {len(rows)} rows")
    coefs = np.asarray(rows, np.float64).T  # (cameras, 11)
    names = [f"cam{i + 1}" for i in range(len(coefs))]
    if sizes is None:
        sizes = _footage_sizes(path, names)
    cameras = []
    for name, c in zip(names, coefs, strict=True):
        if name not in sizes:
            raise CalibrationError(
                f"camera '{name}' in {path}: DLT coefficients hold no image size; put the "
                f"file in the scene folder beside the footage ({name}.mp4 or {name}/)")
        if not np.all(np.isfinite(c)):
            raise CalibrationError(f"camera '{name}' in {path}: non-finite coefficients")
        try:
            cameras.append(_camera(name, c, tuple(sizes[name]), origin, path))
        except (cv2.error, np.linalg.LinAlgError) as e:
            raise CalibrationError(f"camera '{name}' in {path}: degenerate DLT ({e})") from None
    return CameraRig(cameras, source=str(path))


def _image_size(folder: Path, name: str) -> tuple[int, int] | None:
    """(width, height) of camera ``name``'s footage in ``folder`` (a video ``<name>.*`` or
    the first image of ``<name>/``), None when there is none."""
    sub = folder / name
    if sub.is_dir():
        for p in sorted(sub.iterdir()):
            try:
                with Image.open(p) as im:
                    return im.size
            except (OSError, UnidentifiedImageError):
                continue
        return None
    for p in sorted(folder.glob(f"{name}.*")):
        cap = cv2.VideoCapture(str(p))
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        if w > 0 and h > 0:
            return w, h
    return None


def _footage_sizes(path: Path, names: list[str]) -> dict[str, tuple[int, int]]:
    sizes = {}
    for folder in (path.parent, path.parent.parent):
        for name in names:
            if name not in sizes and (size := _image_size(folder, name)) is not None:
                sizes[name] = size
    return sizes


def dlt_from_camera(camera: Camera, origin: str = "lower_left") -> np.ndarray:
    """The 11 DLT coefficients (11,) of a camera without lens distortion."""
    if np.any(camera.dist) or camera.fisheye:
        raise CalibrationError(
            f"camera '{camera.name}': a DLT cannot hold lens distortion; undistort the "
            "footage first or write a format that keeps it (anipose TOML)")
    if camera.size is None:
        raise CalibrationError(f"camera '{camera.name}': writing a DLT needs the image size")
    P = np.linalg.inv(_to_ours(camera.size[1], origin)) @ camera.K @ np.c_[camera.R, camera.t]
    if abs(P[2, 3]) < 1e-12:
        raise CalibrationError(f"camera '{camera.name}': the world origin lies in the camera's "
                               "focal plane, which a DLT cannot express")
    return (P / P[2, 3]).reshape(-1)[:11]


def write_dlt(rig: CameraRig, path: str | os.PathLike, origin: str = "lower_left") -> None:
    """Write ``rig`` as an 11-row DLT coefficient file (cameras in rig order), atomically."""
    cols = np.stack([dlt_from_camera(c, origin) for c in rig], axis=1)  # (11, cameras)
    atomic_write_text(path, "\n".join(",".join(repr(float(v)) for v in row) for row in cols)
                      + "\n")
