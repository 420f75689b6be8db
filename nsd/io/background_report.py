"""The background report of a run: what each camera's background is and where it is unsure.

For every camera, ``<camera>.png`` (the background the decomposition compares frames
with), ``<camera>.uncertain.png`` (the frame at half brightness; in red the pixels where
something stayed for a stretch of the recording and a subject-like colour was kept, in
yellow those where the colour of the frames without it was taken, in blue the other
uncertain pixels, where subjects pass in most frames or stood beside the kept floor), and
one ``report.json`` with the shares (:class:`nsd.cues.background.BackgroundEstimate`). A
large share of stays means a subject stayed in place for part of the recording: the scene
check warns about it by camera (:mod:`nsd.io.scene_check`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsd.core.atomic import atomic_write_bytes, atomic_write_text
from nsd.cues.background import BackgroundEstimate

__all__ = ["uncertainty_image", "write_background_report"]

STAYED = (255, 40, 40)  # RGB of pixels where something stayed, a subject-like colour kept
REPLACED = (255, 220, 0)  # RGB of those where the colour of the frames without it was taken
PASSING = (60, 120, 255)  # RGB of the other uncertain pixels: subjects pass in most frames


def uncertainty_image(background: np.ndarray, uncertain: np.ndarray, replaced: np.ndarray,
                      stayed: np.ndarray) -> np.ndarray:
    """The background at half brightness with its uncertain pixels coloured: (H, W, 3) uint8.

    Example:
        >>> no = np.array([[False, False, False]])
        >>> img = uncertainty_image(np.full((1, 3, 3), 100, np.uint8),
        ...                         np.array([[True, True, False]]), no,
        ...                         np.array([[True, False, False]]))
        >>> img[0].tolist()
        [[255, 40, 40], [60, 120, 255], [50, 50, 50]]
    """
    out = background // 2
    out[uncertain] = PASSING
    out[stayed] = STAYED
    out[replaced] = REPLACED
    return out


def _png(path: Path, rgb: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"cannot encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def write_background_report(
    estimates: Mapping[str, BackgroundEstimate],
    plates: Mapping[str, str],
    out: str | os.PathLike,
    method: str,
) -> dict[str, Any]:
    """Write the background report of a scene's cameras into folder ``out``.

    Args:
        estimates: camera -> its background estimate (:class:`nsd.io.scene_check.SceneCheck`
            holds them); plates: camera -> its plate file; method: ``data.background``.

    Returns:
        what ``report.json`` holds: per camera ``plate`` (its file or None),
        ``uncertain``, ``stayed`` and ``replaced`` shares.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"method": method, "cameras": {}}
    for cam, est in estimates.items():
        _png(out / f"{cam}.png", est.image)
        _png(out / f"{cam}.uncertain.png",
             uncertainty_image(est.image, est.uncertain, est.replaced, est.stayed))
        report["cameras"][cam] = {
            "plate": plates.get(cam),
            "uncertain": round(est.uncertain_share, 6),
            "stayed": round(est.stayed_share, 6),
            "replaced": round(float(est.replaced.mean()), 6),
            "samples": est.samples,
        }
    atomic_write_text(out / "report.json", json.dumps(report, indent=2))
    return report
