"""The calibration's length unit: every rig is used in metres.

The toolkit's distances (``model.association_unit``, ``prior_depth.unit``, the visual hull's
volume, keypoint errors in mm) are metres. Calibrations come in metres (anipose with a
metre board, EasyMocap), millimetres (anipose's default with mm boards, FreeMoCap, SLEAP's
multi-camera data, Qualisys) or centimetres (CMU Panoptic). Formats that state their unit
are converted by their reader; for the others the ``units`` setting says it:

* ``m``, ``cm``, ``mm``: the file's translations are in that unit;
* ``auto`` (default): millimetres when the cameras are a median more than
  :data:`AUTO_MM_SPACING` units apart (no lab rig spans 30 m; a millimetre rig with cameras
  less than 3 cm apart does not exist either), else metres; a conversion is logged and
  noted on the rig (``rig.units_note``), and the scene check repeats it as a warning.
  Centimetres are never guessed (a rig 2 m wide reads 200 units in centimetres, within
  the range of a millimetre rig): give ``units=cm``.
"""

from __future__ import annotations

import logging
from itertools import combinations

import numpy as np

from nsd.cameras.calibration import CameraRig
from nsd.core.errors import CalibrationError

__all__ = ["AUTO_MM_SPACING", "UNITS", "camera_spacing", "file_units", "in_metres"]

log = logging.getLogger(__name__)

UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}  # unit -> metres per unit
_NOTED: set[str] = set()  # calibration files whose inferred unit was warned about
AUTO_MM_SPACING = 30.0  # median camera spacing (file units) above which ``auto`` reads mm


def camera_spacing(rig: CameraRig) -> float:
    """Median distance between the camera centres, in the rig's units (0 for one camera)."""
    centres = [c.center for c in rig]
    if len(centres) < 2:
        return 0.0
    return float(np.median([np.linalg.norm(a - b) for a, b in combinations(centres, 2)]))


def file_units(rig: CameraRig, units: str = "auto") -> str:
    """The unit of a rig as read from its file: ``units`` itself, or what ``auto`` infers
    (``mm`` or ``m``); other files of the scene in that unit (anipose's 3D labels) follow.

    Raises:
        CalibrationError: an unknown unit.
    """
    if units != "auto" and units not in UNITS:
        raise CalibrationError(f"units={units!r}: one of auto, {', '.join(UNITS)}")
    if units != "auto":
        return units
    return "mm" if camera_spacing(rig) > AUTO_MM_SPACING else "m"


def in_metres(rig: CameraRig, units: str = "auto") -> CameraRig:
    """``rig`` with its translations in metres.

    Args:
        rig: as read from the file.
        units: ``auto``, ``m``, ``cm`` or ``mm`` (module docstring).

    Returns:
        The rig in metres (``rig`` itself when it already is); ``units_note`` says what was
        done when the unit was inferred.

    Raises:
        CalibrationError: an unknown unit.
    """
    resolved, note = file_units(rig, units), ""
    if units == "auto" and resolved == "mm":
        note = (f"calibration {rig.source}: the cameras are a median {camera_spacing(rig):.0f} "
                f"units apart, read as millimetres and converted to metres (give units=m, cm "
                f"or mm to say the unit)")
        # every stage reads the calibration again: the warning once per file and process
        (log.debug if str(rig.source) in _NOTED else log.warning)("%s", note)
        _NOTED.add(str(rig.source))
    out = rig if resolved == "m" else rig.with_translation_scale(UNITS[resolved])
    out.units_note = note
    return out
