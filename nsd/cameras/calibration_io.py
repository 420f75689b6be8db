"""Calibration files: read the formats the field writes, write anipose TOML.

Formats
-------
``calibration.toml`` (anipose, Pose2Sim, SLEAP)
    One table per camera, ``[cam_N]`` with ``name``, ``size = [width, height]``,
    ``matrix`` (3x3 K), ``distortions`` (OpenCV order), ``rotation`` (Rodrigues
    vector, world-to-camera) and ``translation`` (world-to-camera). Other tables
    (``[metadata]``) are ignored; ``fisheye = true``: ``distortions`` are the
    Kannala-Brandt k1..k4 of ``cv2.fisheye`` (anipose's fisheye model).
``intri.yml`` + ``extri.yml`` (OpenCV FileStorage, EasyMocap)
    ``names`` (sequence of camera names); ``K_<name>``, ``dist_<name>`` and
    optionally ``H_<name>``/``W_<name>`` in ``intri.yml``; ``Rot_<name>`` (3x3)
    or ``R_<name>`` (Rodrigues) and ``T_<name>`` in ``extri.yml``.
``*.qca.txt`` (Qualisys, as exported in Pose2Sim's demos)
    XML. Focal lengths, principal point and distortion (k1, k2, p1, p2) are
    stored x64; the principal point is relative to the sensor, so the
    ``fov_video`` left/top offset is subtracted; the image is the ``fov_video``
    window. ``transform`` holds the camera-to-world rotation (entries listed
    column by column) and the camera position in millimetres; the camera frame
    is OpenCV's rotated by pi about x. We convert to OpenCV world-to-camera,
    metres.

caliscope / FreeMoCap ``camera_array.toml``, CMU Panoptic JSON and COLMAP models
    :mod:`nsd.cameras.calibration_formats`.

Distortion: OpenCV's 4, 5, 8, 12 (thin prism) and 14 (tilted sensor) coefficient models, and
the Kannala-Brandt fisheye (anipose TOML, COLMAP OPENCV_FISHEYE); formats that cannot hold a
fisheye lens refuse to write one.
All readers return a validated :class:`~nsd.cameras.calibration.CameraRig`; bad values
raise :class:`~nsd.core.errors.CalibrationError` naming the file and camera.
"""

from __future__ import annotations

import json
import os
import tempfile
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import tomli_w

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_formats import (
    camera_from_file,
    read_caliscope,
    read_colmap,
    read_panoptic,
    refuse_fisheye,
    write_caliscope,
    write_colmap,
    write_panoptic,
)
from nsd.cameras.dlt import read_dlt, write_dlt
from nsd.cameras.units import in_metres
from nsd.core.atomic import atomic_write_text
from nsd.core.errors import CalibrationError

__all__ = [
    "WRITERS",
    "find_calibration",
    "read_calibration",
    "read_opencv_yaml",
    "read_qca",
    "read_toml",
    "write_calibration",
    "write_opencv_yaml",
    "write_toml",
]

QCA_SCALE = 64.0  # Qualisys stores focal, principal point and distortion x64
QCA_UNITS_TO_METRES = 1e-3


def _rodrigues(rvec, source: Path, name: str) -> np.ndarray:
    rvec = np.asarray(rvec, dtype=np.float64).reshape(-1)
    if rvec.size != 3 or not np.all(np.isfinite(rvec)):
        raise CalibrationError(
            f"camera '{name}' in {source}: rotation must be 3 finite numbers, got {rvec}"
        )
    return cv2.Rodrigues(rvec)[0]


# --------------------------------------------------------------------------- TOML
def read_toml(path: str | os.PathLike) -> CameraRig:
    """Read an anipose/Pose2Sim/SLEAP ``calibration.toml``."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"calibration file {path} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{path} is not valid TOML: {e}") from e
    cameras = []
    for key, table in data.items():
        if key == "metadata" or not isinstance(table, dict):
            continue
        name = str(table.get("name", key))
        missing = [k for k in ("matrix", "rotation", "translation") if k not in table]
        if missing:
            raise CalibrationError(f"camera '{name}' ([{key}]) in {path}: missing {missing}")
        size = table.get("size")
        cameras.append(
            camera_from_file(
                path,
                name,
                K=np.asarray(table["matrix"], dtype=np.float64),
                dist=np.asarray(table.get("distortions", []), dtype=np.float64),
                R=_rodrigues(table["rotation"], path, name),
                t=np.asarray(table["translation"], dtype=np.float64),
                size=None if size is None else (int(size[0]), int(size[1])),
                fisheye=bool(table.get("fisheye", False)),
            )
        )
    return CameraRig(cameras, source=str(path))


def write_toml(rig: CameraRig, path: str | os.PathLike) -> None:
    """Write ``rig`` as an anipose-style ``calibration.toml`` (atomically)."""
    data: dict = {}
    for i, c in enumerate(rig):
        table = {
            "name": c.name,
            "matrix": c.K.tolist(),
            "distortions": c.dist.tolist(),
            "rotation": cv2.Rodrigues(c.R)[0].reshape(-1).tolist(),
            "translation": c.t.tolist(),
        }
        if c.size is not None:
            table["size"] = list(c.size)
        if c.fisheye:
            table["fisheye"] = True
        data[f"cam_{i}"] = table
    data["metadata"] = {"adjusted": False, "error": 0.0}
    atomic_write_text(path, tomli_w.dumps(data))


# --------------------------------------------------------------------------- OpenCV YAML
def _fs_open(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise CalibrationError(f"{path} is not an OpenCV FileStorage file: {e}") from e
    if not fs.isOpened():
        raise CalibrationError(f"{path} is not an OpenCV FileStorage file")
    return fs


def _fs_names(fs: cv2.FileStorage, path: Path) -> list[str]:
    node = fs.getNode("names")
    if node.empty():
        raise CalibrationError(f"{path}: no 'names' list of cameras")
    return [node.at(i).string() or str(int(node.at(i).real())) for i in range(node.size())]


def _fs_mat(fs: cv2.FileStorage, key: str, path: Path, required: bool = True):
    node = fs.getNode(key)
    mat = None if node.empty() else node.mat()
    if mat is None and node is not None and not node.empty() and node.isReal():
        mat = np.array([node.real()])
    if mat is None and required:
        raise CalibrationError(f"{path}: missing '{key}'")
    return mat


def read_opencv_yaml(intri: str | os.PathLike, extri: str | os.PathLike | None = None) -> CameraRig:
    """Read EasyMocap-style ``intri.yml`` and ``extri.yml`` (OpenCV FileStorage).

    Args:
        intri: path of ``intri.yml``, or a folder holding both files.
        extri: path of ``extri.yml``; defaults to the sibling of ``intri``.
    """
    intri = Path(intri)
    if intri.is_dir():
        intri = intri / "intri.yml"
    extri = Path(extri) if extri is not None else intri.with_name("extri.yml")
    fi, fe = _fs_open(intri), _fs_open(extri)
    names = _fs_names(fi, intri)
    cameras = []
    for n in names:
        K = _fs_mat(fi, f"K_{n}", intri)
        dist = _fs_mat(fi, f"dist_{n}", intri, required=False)
        rot = _fs_mat(fe, f"Rot_{n}", extri, required=False)
        R = rot if rot is not None else _rodrigues(_fs_mat(fe, f"R_{n}", extri), extri, n)
        T = _fs_mat(fe, f"T_{n}", extri)
        H, W = fi.getNode(f"H_{n}"), fi.getNode(f"W_{n}")
        size = None if H.empty() or W.empty() else (int(W.real()), int(H.real()))
        cameras.append(
            camera_from_file(
                intri,
                n,
                K=K,
                dist=np.zeros(0) if dist is None else dist.reshape(-1),
                R=R,
                t=T.reshape(-1),
                size=size,
            )
        )
    return CameraRig(cameras, source=str(intri))


def write_opencv_yaml(rig: CameraRig, folder: str | os.PathLike) -> None:
    """Write ``intri.yml`` and ``extri.yml`` (EasyMocap layout) into ``folder``."""
    refuse_fisheye(rig, "OpenCV FileStorage")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for fname, write in (("intri.yml", _write_intri), ("extri.yml", _write_extri)):
        # cv2.FileStorage cannot write to a file object: write a temporary file, then move it.
        fd, tmp = tempfile.mkstemp(suffix=".yml", dir=folder, prefix=f".{fname}.")
        os.close(fd)
        try:
            fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
            fs.startWriteStruct("names", cv2.FileNode_SEQ)
            for c in rig:
                fs.write("", c.name)
            fs.endWriteStruct()
            write(fs, rig)
            fs.release()
            os.replace(tmp, folder / fname)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)


def _write_intri(fs: cv2.FileStorage, rig: CameraRig) -> None:
    for c in rig:
        fs.write(f"K_{c.name}", c.K)
        fs.write(f"dist_{c.name}", c.dist.reshape(1, -1))
        if c.size is not None:
            fs.write(f"W_{c.name}", int(c.size[0]))
            fs.write(f"H_{c.name}", int(c.size[1]))


def _write_extri(fs: cv2.FileStorage, rig: CameraRig) -> None:
    for c in rig:
        fs.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
        fs.write(f"Rot_{c.name}", c.R)
        fs.write(f"T_{c.name}", c.t.reshape(3, 1))


# --------------------------------------------------------------------------- Qualisys
_ROT_PI_X = np.diag([1.0, -1.0, -1.0])  # Qualisys camera frame -> OpenCV camera frame


def read_qca(path: str | os.PathLike) -> CameraRig:
    """Read a Qualisys ``*.qca.txt`` calibration (see the module docstring)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise CalibrationError(f"calibration file {path} does not exist") from None
    except ET.ParseError as e:
        raise CalibrationError(f"{path} is not a Qualisys XML calibration: {e}") from e
    cameras = []
    for cam in root.findall("cameras/camera"):
        name = cam.get("serial") or f"cam{len(cameras) + 1:02d}"
        fov, intr, tr = cam.find("fov_video"), cam.find("intrinsic"), cam.find("transform")
        if fov is None or intr is None or tr is None:
            raise CalibrationError(
                f"camera '{name}' in {path}: needs fov_video, intrinsic and transform"
            )
        try:
            left, top = float(fov.get("left")), float(fov.get("top"))
            width = round(float(fov.get("right")) - left + 1)
            height = round(float(fov.get("bottom")) - top + 1)
            f = {
                k: float(intr.get(k))
                for k in ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV")
            }
            d = [
                float(intr.get(k)) / QCA_SCALE
                for k in (
                    "radialDistortion1",
                    "radialDistortion2",
                    "tangentalDistortion1",
                    "tangentalDistortion2",
                )
            ]
            r = np.array([float(tr.get(f"r{i}{j}")) for i in (1, 2, 3) for j in (1, 2, 3)])
            pos = np.array([float(tr.get(k)) for k in ("x", "y", "z")]) * QCA_UNITS_TO_METRES
        except (TypeError, ValueError) as e:
            raise CalibrationError(f"camera '{name}' in {path}: missing or bad value ({e})") from e
        K = np.array(
            [
                [f["focalLengthU"] / QCA_SCALE, 0.0, f["centerPointU"] / QCA_SCALE - left],
                [0.0, f["focalLengthV"] / QCA_SCALE, f["centerPointV"] / QCA_SCALE - top],
                [0.0, 0.0, 1.0],
            ]
        )
        cam_to_world = r.reshape(3, 3).T  # entries are listed column by column
        R = _ROT_PI_X @ cam_to_world.T
        t = -R @ pos
        cameras.append(camera_from_file(path, name, K=K, dist=np.array(d), R=R, t=t,
                                        size=(width, height)))
    if not cameras:
        raise CalibrationError(f"{path}: no <camera> entries")
    return CameraRig(cameras, source=str(path))


# --------------------------------------------------------------------------- dispatch
def _calibration_toml(path: Path) -> str | None:
    """``anipose`` or ``caliscope`` when the TOML file holds cameras, else None (e.g. a
    Pose2Sim ``Config.toml`` beside its ``calibration/`` folder)."""
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
        return None
    if isinstance(data.get("cameras"), dict):
        return "caliscope"
    if any(isinstance(t, dict) and "matrix" in t for t in data.values()):
        return "anipose"
    return None


def _panoptic_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return False
    return isinstance(data, dict) and isinstance(data.get("cameras"), list)


def find_calibration(scene: str | os.PathLike) -> Path:
    """The calibration file of a scene folder.

    Looks in the folder, then in its ``calibration/`` subfolder (Pose2Sim's layout) and
    ``sparse/0/`` (COLMAP's), for, in this order: ``calibration.toml``, a caliscope
    ``camera_array.toml``, any other TOML file that holds cameras (so a Pose2Sim
    ``Config.toml`` is passed over), ``intri.yml``, ``*.qca.txt``, a CMU Panoptic
    ``calibration*.json``, a COLMAP ``cameras.txt`` / ``cameras.bin`` and a DLT coefficient
    file (``*dlt*.csv``, any case: Argus ``*_dlt-coefs.csv``, DLTdv, easyWand).
    """
    scene = Path(scene)
    for folder in (scene, scene / "calibration", scene / "sparse" / "0"):
        if not folder.is_dir():
            continue
        tomls = sorted(folder.glob("*.toml"), key=lambda p: (
            p.name != "calibration.toml", p.name != "camera_array.toml", p.name))
        for p in tomls:
            if _calibration_toml(p):
                return p
        for pattern in ("intri.yml", "*.qca.txt", "calibration*.json", "cameras.txt",
                        "cameras.bin", "*.csv"):
            hits = [p for p in sorted(folder.glob(pattern))
                    if (not p.name.endswith(".json") or _panoptic_json(p))
                    and (not p.name.endswith(".csv") or "dlt" in p.name.lower())]
            if hits:
                return hits[0]
    raise CalibrationError(
        f"no calibration file in {scene} (expected calibration.toml, camera_array.toml, "
        "intri.yml + extri.yml, *.qca.txt, a Panoptic calibration*.json, a COLMAP "
        "cameras.txt/.bin or DLT coefficients *dlt*.csv, in the scene folder or its "
        "calibration/ subfolder)"
    )


def read_calibration(path: str | os.PathLike, units: str = "auto") -> CameraRig:
    """Read any supported calibration file (by name and content), or find one in a folder;
    the rig comes back in metres (``units``: ``auto``, ``m``, ``cm`` or ``mm``, the file's
    length unit where the format does not state it; :mod:`nsd.cameras.units`)."""
    return in_metres(_read_file(Path(path)), units)


def _read_file(path: Path) -> CameraRig:
    """The rig as the file holds it (formats that state their unit converted to metres)."""
    if path.is_dir():
        path = find_calibration(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist")
    name = path.name.lower()
    if name.endswith(".toml"):
        return read_caliscope(path) if _calibration_toml(path) == "caliscope" else read_toml(path)
    if name.endswith(".qca.txt"):
        return read_qca(path)
    if name.endswith((".yml", ".yaml")):
        return read_opencv_yaml(path)
    if name.endswith(".json"):
        return read_panoptic(path)
    if name in ("cameras.txt", "cameras.bin", "images.txt", "images.bin"):
        return read_colmap(path.parent)
    if name.endswith(".csv"):
        return read_dlt(path)
    raise CalibrationError(
        f"{path}: unknown calibration format (.toml, .yml, .qca.txt, .json, COLMAP "
        "cameras.txt, DLT .csv)")


# format -> writer(rig, path); folder formats take a folder
WRITERS = {
    "anipose": write_toml,
    "caliscope": write_caliscope,
    "opencv": write_opencv_yaml,
    "panoptic": write_panoptic,
    "colmap": write_colmap,
    "colmap_bin": lambda rig, folder: write_colmap(rig, folder, binary=True),
    "dlt": write_dlt,
}


def write_calibration(rig: CameraRig, path: str | os.PathLike, format: str = "auto") -> str:
    """Write ``rig`` in any writable format; ``auto`` picks it by the name (``*.toml``:
    anipose, ``camera_array.toml``: caliscope, ``*.json``: Panoptic, ``*.csv``: DLT).
    Returns the format.

    Raises:
        CalibrationError: an unknown format, or ``auto`` for a name that does not say one.
    """
    path = Path(path)
    if format == "auto":
        name = path.name.lower()
        format = ("caliscope" if name == "camera_array.toml" else "anipose"
                  if name.endswith(".toml") else "panoptic" if name.endswith(".json")
                  else "dlt" if name.endswith(".csv") else "")
        if not format:
            raise CalibrationError(
                f"{path}: give the format ({', '.join(WRITERS)}); a folder name does not say it")
    if format not in WRITERS:
        raise CalibrationError(f"unknown calibration format {format!r}; one of {list(WRITERS)}")
    WRITERS[format](rig, path)
    return format
