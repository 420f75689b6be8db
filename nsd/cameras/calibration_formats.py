"""More calibration formats: caliscope / FreeMoCap, CMU Panoptic, COLMAP (text and binary).

Each format has a reader (file -> :class:`~nsd.cameras.calibration.CameraRig`, OpenCV
conventions, metres) and a writer (the inverse, for round trips and conversion). The
dispatch by file name and content is :func:`nsd.cameras.calibration_io.read_calibration`.

``camera_array.toml`` (caliscope, FreeMoCap)
    ``[cameras.<id>]`` tables with ``size``, ``matrix``, ``distortions``, ``rotation``
    (3x3, world-to-camera) and ``translation``; cameras are named ``cam_<id>``.
``calibration_<sequence>.json`` (CMU Panoptic)
    ``{"cameras": [{"name", "resolution", "K", "distCoef", "R", "t"}]}``; ``R``, ``t``
    world-to-camera, ``t`` in centimetres (converted to metres).
COLMAP ``cameras.txt`` + ``images.txt`` (or ``.bin``) in one folder
    one image per camera (a rig registered from one frame of each camera); the camera is
    named after the image's folder (``cam0/000000.png`` -> ``cam0``), else its file stem.
    Models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV; COLMAP's
    pixel centres are at +0.5 (OpenCV's at 0), so 0.5 is subtracted from the principal
    point. Poses: quaternion (w, x, y, z) and translation, world-to-camera; SfM units.
"""

from __future__ import annotations

import json
import os
import struct
import tomllib
from pathlib import Path

import numpy as np
import tomli_w

from nsd.cameras.calibration import Camera, CameraRig
from nsd.core.atomic import atomic_write_bytes, atomic_write_text
from nsd.core.errors import CalibrationError

__all__ = [
    "COLMAP_MODELS",
    "camera_from_file",
    "read_caliscope",
    "read_colmap",
    "read_panoptic",
    "write_caliscope",
    "write_colmap",
    "write_panoptic",
]

PANOPTIC_UNITS_TO_METRES = 0.01  # Panoptic's translations are centimetres
COLMAP_PIXEL_CENTRE = 0.5  # COLMAP's top-left pixel centre is (0.5, 0.5); OpenCV's (0, 0)
# model name -> (id, number of parameters)
COLMAP_MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4),
                 "RADIAL": (3, 5), "OPENCV": (4, 8), "OPENCV_FISHEYE": (5, 8),
                 "FULL_OPENCV": (6, 12)}
_COLMAP_BY_ID = {i: (name, n) for name, (i, n) in COLMAP_MODELS.items()}
_COLMAP_UNSUPPORTED = {7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE",
                       9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE"}


def refuse_fisheye(rig: CameraRig, format: str) -> None:
    """A format that cannot hold a Kannala-Brandt lens refuses to write one (no silent
    misreading of k1..k4 as OpenCV's k1, k2, p1, p2 later)."""
    for c in rig:
        if c.fisheye:
            raise CalibrationError(
                f"camera '{c.name}' has a fisheye lens, which the {format} format cannot hold; "
                "write anipose TOML (calibration.toml) or COLMAP (OPENCV_FISHEYE) instead")


def camera_from_file(source: Path, name: str, **kw) -> Camera:
    """A validated :class:`Camera` read from ``source``; bad values name the file and camera."""
    try:
        return Camera(name=name, source=str(source), **kw)
    except CalibrationError:
        raise
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"camera '{name}' in {source}: {e}") from e


# --------------------------------------------------------------------------- caliscope
def read_caliscope(path: str | os.PathLike) -> CameraRig:
    """Read a caliscope / FreeMoCap ``camera_array.toml``."""
    path = Path(path)
    try:
        tables = tomllib.loads(path.read_text()).get("cameras", {})
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{path} is not valid TOML: {e}") from e
    cameras = []
    for key in sorted(tables, key=lambda k: (len(k), k)):
        t = tables[key]
        name = f"cam_{key}"
        if t.get("ignore", False):
            continue
        missing = [k for k in ("matrix", "rotation", "translation") if k not in t]
        if missing:
            raise CalibrationError(f"camera '{name}' ([cameras.{key}]) in {path}: missing "
                                   f"{missing} (not yet calibrated?)")
        size = t.get("size")
        cameras.append(camera_from_file(
            path, name, K=np.asarray(t["matrix"], np.float64),
            dist=np.asarray(t.get("distortions", []), np.float64),
            R=np.asarray(t["rotation"], np.float64), t=np.asarray(t["translation"], np.float64),
            size=None if size is None else (int(size[0]), int(size[1]))))
    if not cameras:
        raise CalibrationError(f"{path}: no [cameras.<id>] table")
    return CameraRig(cameras, source=str(path))


def write_caliscope(rig: CameraRig, path: str | os.PathLike) -> None:
    """Write ``rig`` as a caliscope ``camera_array.toml`` (cameras numbered in order)."""
    refuse_fisheye(rig, "caliscope")
    tables = {}
    for i, c in enumerate(rig):
        t = {"cam_id": i, "matrix": c.K.tolist(), "distortions": c.dist.tolist(),
             "rotation": c.R.tolist(), "translation": c.t.tolist()}
        if c.size is not None:
            t["size"] = list(c.size)
        tables[str(i)] = t
    atomic_write_text(path, tomli_w.dumps({"cameras": tables}))


# --------------------------------------------------------------------------- Panoptic
def read_panoptic(path: str | os.PathLike) -> CameraRig:
    """Read a CMU Panoptic ``calibration_<sequence>.json`` (every camera it lists)."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())["cameras"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise CalibrationError(f"{path} is not a Panoptic calibration ({e})") from e
    cameras = []
    for e in entries:
        name = str(e.get("name", len(cameras)))
        try:
            res = e.get("resolution")
            cameras.append(camera_from_file(
                path, name, K=np.asarray(e["K"], np.float64),
                dist=np.asarray(e.get("distCoef", []), np.float64),
                R=np.asarray(e["R"], np.float64),
                t=np.asarray(e["t"], np.float64).reshape(-1) * PANOPTIC_UNITS_TO_METRES,
                size=None if res is None else (int(res[0]), int(res[1]))))
        except KeyError as k:
            raise CalibrationError(f"camera '{name}' in {path}: missing {k}") from None
    return CameraRig(cameras, source=str(path))


def write_panoptic(rig: CameraRig, path: str | os.PathLike) -> None:
    """Write ``rig`` as a Panoptic calibration JSON (translations in centimetres)."""
    refuse_fisheye(rig, "Panoptic")
    entries = [{"name": c.name, "type": "hd", "resolution": list(c.size) if c.size else None,
                "K": c.K.tolist(), "distCoef": c.dist.tolist(), "R": c.R.tolist(),
                "t": (c.t / PANOPTIC_UNITS_TO_METRES).reshape(3, 1).tolist()} for c in rig]
    atomic_write_text(path, json.dumps({"calibDataSource": "nsd-netepu", "cameras": entries},
                                       indent=1))


# --------------------------------------------------------------------------- COLMAP
def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, w >= 0 (Shepperd's method)."""
    tr = np.trace(R)
    if tr > 0:
        s = 2 * np.sqrt(1 + tr)
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i], q[1 + j], q[1 + k] = s / 4, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    q = np.asarray(q, np.float64)
    return q if q[0] >= 0 else -q


def _intrinsics(model: str, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K (OpenCV pixel centres) and OpenCV distortion of a COLMAP camera model."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, rest = p[1], p[2], p[3:]
        dist = [] if model == "SIMPLE_PINHOLE" else [*rest, 0.0, 0.0, 0.0, 0.0][:4]
    else:
        fx, fy, cx, cy, rest = p[0], p[1], p[2], p[3], p[4:]
        dist = list(rest)  # PINHOLE: none; OPENCV: k1 k2 p1 p2; FULL_OPENCV: + k3..k6;
        # OPENCV_FISHEYE: Kannala-Brandt k1..k4
    K = np.array([[fx, 0, cx - COLMAP_PIXEL_CENTRE], [0, fy, cy - COLMAP_PIXEL_CENTRE],
                  [0, 0, 1]])
    return K, np.asarray(dist, np.float64)


def _view_name(image_name: str) -> str:
    parts = Path(image_name).parts
    return parts[0] if len(parts) > 1 else Path(image_name).stem


def _read_colmap_text(folder: Path) -> tuple[dict, list]:
    cams, images = {}, []
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            f = line.split()
            cams[int(f[0])] = (f[1], int(f[2]), int(f[3]), np.asarray(f[4:], np.float64))
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines()
             if not ln.startswith("#")]
    for line in lines[::2]:  # every image line is followed by its 2D points' line
        f = line.split()
        if len(f) >= 10:
            images.append((np.asarray(f[1:5], np.float64), np.asarray(f[5:8], np.float64),
                           int(f[8]), " ".join(f[9:])))
    return cams, images


def _read_colmap_binary(folder: Path) -> tuple[dict, list]:
    cams, images = {}, []
    data = (folder / "cameras.bin").read_bytes()
    (n,), off = struct.unpack_from("<Q", data), 8
    for _ in range(n):
        cam_id, model_id, w, h = struct.unpack_from("<iiQQ", data, off)
        off += 24
        if model_id not in _COLMAP_BY_ID:
            name = _COLMAP_UNSUPPORTED.get(model_id, f"model id {model_id}")
            raise CalibrationError(f"{folder / 'cameras.bin'}: camera {cam_id} uses COLMAP's "
                                   f"{name} model; supported: {sorted(COLMAP_MODELS)}")
        model, k = _COLMAP_BY_ID[model_id]
        cams[cam_id] = (model, w, h, np.asarray(struct.unpack_from(f"<{k}d", data, off)))
        off += 8 * k
    data = (folder / "images.bin").read_bytes()
    (n,), off = struct.unpack_from("<Q", data), 8
    for _ in range(n):
        _, *qt, cam_id = struct.unpack_from("<i7di", data, off)
        off += 64
        end = data.index(b"\0", off)
        name, off = data[off:end].decode(), end + 1
        (points,) = struct.unpack_from("<Q", data, off)
        off += 8 + 24 * points
        images.append((np.asarray(qt[:4]), np.asarray(qt[4:]), cam_id, name))
    return cams, images


def read_colmap(folder: str | os.PathLike) -> CameraRig:
    """Read a COLMAP model folder (``cameras.txt``/``images.txt`` or the ``.bin`` pair)."""
    folder = Path(folder)
    source = folder / ("cameras.txt" if (folder / "cameras.txt").is_file() else "cameras.bin")
    try:
        if source.suffix == ".txt":
            cams, images = _read_colmap_text(folder)
        else:
            cams, images = _read_colmap_binary(folder)
    except (OSError, ValueError, IndexError, struct.error) as e:
        raise CalibrationError(f"{folder}: not a readable COLMAP model ({e})") from e
    cameras = []
    for q, t, cam_id, image_name in sorted(images, key=lambda im: im[3]):
        name = _view_name(image_name)
        if cam_id not in cams:
            raise CalibrationError(f"{folder}: image {image_name} names camera {cam_id}, "
                                   "which cameras.* does not hold")
        model, w, h, params = cams[cam_id]
        if model not in COLMAP_MODELS:
            raise CalibrationError(f"{source}: camera {cam_id} uses COLMAP's {model} model; "
                                   f"supported: {sorted(COLMAP_MODELS)}")
        K, dist = _intrinsics(model, params)
        cameras.append(camera_from_file(source, name, K=K, dist=dist, R=_quat_to_matrix(q), t=t,
                                        size=(int(w), int(h)),
                                        fisheye=model == "OPENCV_FISHEYE"))
    if not cameras:
        raise CalibrationError(f"{folder}: the COLMAP model registers no image")
    return CameraRig(cameras, source=str(source))


def _colmapcamera_from_file(c: Camera) -> tuple[str, list[float]]:
    """FULL_OPENCV, OPENCV or PINHOLE parameters of a camera (skew must be 0)."""
    if abs(c.K[0, 1]) > 1e-12:
        raise CalibrationError(f"camera '{c.name}': COLMAP models have no skew")
    f = [c.K[0, 0], c.K[1, 1], c.K[0, 2] + COLMAP_PIXEL_CENTRE, c.K[1, 2] + COLMAP_PIXEL_CENTRE]
    d = list(c.dist)
    if c.fisheye:
        return "OPENCV_FISHEYE", f + d
    if not any(d):
        return "PINHOLE", f
    if len(d) > 8:
        raise CalibrationError(f"camera '{c.name}': {len(d)} distortion coefficients do not "
                               "fit a COLMAP model (at most 8: FULL_OPENCV)")
    if len(d) <= 4:
        return "OPENCV", f + (d + [0.0] * 4)[:4]
    return "FULL_OPENCV", f + (d + [0.0] * 8)[:8]


def write_colmap(rig: CameraRig, folder: str | os.PathLike, binary: bool = False) -> None:
    """Write ``rig`` as a COLMAP model (one camera and one image ``<name>/000000.png`` per
    camera), as text or binary."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, c in enumerate(rig, start=1):
        if c.size is None:
            raise CalibrationError(f"camera '{c.name}': COLMAP needs the image size")
        model, params = _colmapcamera_from_file(c)
        rows.append((i, model, c.size, params, _matrix_to_quat(c.R), c.t, f"{c.name}/000000.png"))
    if binary:
        cams = struct.pack("<Q", len(rows)) + b"".join(
            struct.pack(f"<iiQQ{len(p)}d", i, COLMAP_MODELS[m][0], s[0], s[1], *p)
            for i, m, s, p, *_ in rows)
        imgs = struct.pack("<Q", len(rows)) + b"".join(
            struct.pack("<i7di", i, *q, *t, i) + name.encode() + b"\0" + struct.pack("<Q", 0)
            for i, _, _, _, q, t, name in rows)
        atomic_write_bytes(folder / "cameras.bin", cams)
        atomic_write_bytes(folder / "images.bin", imgs)
        return
    cams = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"] + [
        f"{i} {m} {s[0]} {s[1]} " + " ".join(repr(float(v)) for v in p)
        for i, m, s, p, *_ in rows]
    imgs = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, _, _, _, q, t, name in rows:
        imgs += [f"{i} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {i} {name}", ""]
    atomic_write_text(folder / "cameras.txt", "\n".join(cams) + "\n")
    atomic_write_text(folder / "images.txt", "\n".join(imgs) + "\n")
