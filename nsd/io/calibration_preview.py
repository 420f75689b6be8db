"""See a calibration before training: the rig as a table and as a picture.

:func:`rig_table` lists every camera (size, focal length, principal point, distortion,
centre, viewing direction, distance to the point the cameras look at). :func:`preview`
draws the cameras from above and from the side with the floor grid (the plane z = 0,
world z up), and one frame of each camera with that grid and the world axes reprojected
through the calibration (distortion included). A unit mistake (millimetres), a y-up
world or a wrong camera name shows at once: the grid is not on the floor, the axes point
the wrong way, the grid misses the image.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from nsd.cameras.calibration import CameraRig

__all__ = ["look_at_point", "preview", "rig_table"]

PANEL = 360  # pixels of the longer side of every panel
GRID_COLOUR = (90, 200, 90)  # RGB
AXES = ((255, 60, 60), (60, 200, 60), (70, 110, 255))  # x, y, z (RGB)


def look_at_point(rig: CameraRig) -> np.ndarray:
    """The point closest, in least squares, to every camera's optical axis (3,)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in rig:
        d = c.viewing_direction / np.linalg.norm(c.viewing_direction)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def rig_table(rig: CameraRig) -> str:
    """A Markdown table of the rig, one camera per row."""
    target = look_at_point(rig)
    rows = ["| camera | size | f (px) | principal point | distortion | centre | looks along | "
            "distance to target |", "|---|---|---|---|---|---|---|---|"]
    for c in rig:
        size = f"{c.size[0]}x{c.size[1]}" if c.size else "?"
        d = c.viewing_direction / np.linalg.norm(c.viewing_direction)
        lens = f"{c.dist.size} coeff." + (" fisheye" if c.fisheye else "")
        rows.append(
            f"| {c.name} | {size} | {c.K[0, 0]:.1f}, {c.K[1, 1]:.1f} | "
            f"{c.K[0, 2]:.1f}, {c.K[1, 2]:.1f} | {lens} | "
            f"{', '.join(f'{v:.3f}' for v in c.center)} | {', '.join(f'{v:.2f}' for v in d)} | "
            f"{np.linalg.norm(c.center - target):.3f} |")
    target = np.round(target, 3) + 0.0  # no -0.0
    return "\n".join(rows) + f"\n\nThe optical axes meet nearest {target.tolist()}.\n"


def _nice_step(extent: float) -> float:
    """A round grid spacing giving about 10 cells over ``extent``."""
    raw = max(extent, 1e-9) / 10
    base = 10 ** math.floor(math.log10(raw))
    return base * min((1, 2, 5, 10), key=lambda m: abs(m * base - raw))


def _floor_grid(rig: CameraRig) -> tuple[list[np.ndarray], float]:
    """Polylines (each (S, 3)) of the z = 0 grid around the rig's target, and the spacing."""
    target = look_at_point(rig)
    half = float(np.median([np.linalg.norm(c.center[:2] - target[:2]) for c in rig])) or 1.0
    step = _nice_step(2 * half)
    n = math.ceil(half / step)
    cx, cy = (round(v / step) * step for v in target[:2])
    ticks = np.arange(-n, n + 1) * step
    s = np.linspace(-n * step, n * step, 60)
    lines = [np.stack([np.full_like(s, cx + k), cy + s, np.zeros_like(s)], 1) for k in ticks]
    lines += [np.stack([cx + s, np.full_like(s, cy + k), np.zeros_like(s)], 1) for k in ticks]
    return lines, step


def _plan(rig: CameraRig, axes: tuple[int, int], title: str) -> np.ndarray:
    """Cameras seen along the remaining axis (0 x, 1 y, 2 z): dots, axes and the grid."""
    lines, _ = _floor_grid(rig)
    pts = np.concatenate([*(ln for ln in lines), np.stack([c.center for c in rig])])[:, axes]
    lo, hi = pts.min(0), pts.max(0)
    scale = (PANEL - 40) / max(float((hi - lo).max()), 1e-9)
    img = np.full((PANEL, PANEL, 3), 255, np.uint8)

    def px(p: np.ndarray) -> tuple[int, int]:
        q = (np.asarray(p)[list(axes)] - lo) * scale + 20
        return int(q[0]), int(PANEL - q[1])  # second axis up

    for ln in lines:
        cv2.line(img, px(ln[0]), px(ln[-1]), (210, 225, 210), 1)
    for c in rig:
        d = c.viewing_direction / np.linalg.norm(c.viewing_direction)
        tip = c.center + d * 0.15 * (hi - lo).max()
        cv2.arrowedLine(img, px(c.center), px(tip), (40, 40, 200), 2, tipLength=0.25)
        cv2.circle(img, px(c.center), 4, (0, 0, 0), -1)
        cv2.putText(img, c.name, px(c.center), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(img, title, (8, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return img


def _camera_panel(rig: CameraRig, v: int, frame: np.ndarray | None) -> np.ndarray:
    """Camera ``v``'s frame (or a grey canvas) with the floor grid and world axes drawn."""
    cam = rig[v]
    w, h = cam.size if cam.size else (640, 480)
    img = frame.copy() if frame is not None else np.full((h, w, 3), 128, np.uint8)
    lines, step = _floor_grid(rig)
    thick = max(1, round(max(w, h) / 400))

    def draw(points: np.ndarray, colour: tuple[int, int, int], width: int) -> None:
        uv, z = cam.project(points)
        ok = (z > 0) & np.isfinite(uv).all(1) & (np.abs(uv) < 4 * max(w, h)).all(1)
        for a, b in zip(range(len(uv) - 1), range(1, len(uv)), strict=True):
            if ok[a] and ok[b]:
                cv2.line(img, tuple(np.round(uv[a]).astype(int)),
                         tuple(np.round(uv[b]).astype(int)), colour, width, cv2.LINE_AA)

    for ln in lines:
        draw(ln, GRID_COLOUR, thick)
    origin = np.zeros(3)
    for axis, colour in enumerate(AXES):  # world axes, one grid cell long
        end = origin.copy()
        end[axis] = step
        draw(np.linspace(origin, end, 20), colour, 2 * thick)
    scale = PANEL / max(w, h)
    img = cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    cv2.putText(img, cam.name, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1)
    return img


def preview(rig: CameraRig, frames: list[np.ndarray | None] | None = None) -> np.ndarray:
    """The rig from above (x-y) and from the side (x-z), then every camera's view: RGB (H, W, 3).

    Args:
        rig: the calibration.
        frames: one RGB frame per camera at its calibrated size (None: grey canvases).
    """
    frames = frames if frames is not None else [None] * len(rig)
    panels = [_plan(rig, (0, 1), "from above (x right, y up)"),
              _plan(rig, (0, 2), "from the side (x right, z up)")]
    panels += [_camera_panel(rig, v, f) for v, f in enumerate(frames)]
    cols = min(4, len(panels))
    rows = math.ceil(len(panels) / cols)
    out = np.full((rows * (PANEL + 4), cols * (PANEL + 4), 3), 255, np.uint8)
    for i, p in enumerate(panels):
        r, c = divmod(i, cols)
        out[r * (PANEL + 4): r * (PANEL + 4) + p.shape[0],
            c * (PANEL + 4): c * (PANEL + 4) + p.shape[1]] = p
    return out
