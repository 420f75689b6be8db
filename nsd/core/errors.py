"""Exception types of the toolkit.

Every error names what was wrong and where (file, camera, frame) and, where
possible, what to do about it. They subclass :class:`ValueError` so that callers
that only know the standard library can still catch them.
"""

from __future__ import annotations

__all__ = [
    "BAD_INPUT_ERRORS",
    "CalibrationError",
    "CheckpointError",
    "ConfigError",
    "FootageError",
    "NSDError",
    "NonFiniteError",
    "RunFolderBusyError",
    "SceneError",
]


class NSDError(ValueError):
    """Base class of every error raised on bad input."""


class CalibrationError(NSDError):
    """A calibration file or camera is unreadable or physically impossible."""


class FootageError(NSDError):
    """A scene folder, video or image folder cannot be used."""


class ConfigError(NSDError):
    """A configuration value is out of its documented range."""


class CheckpointError(NSDError):
    """A checkpoint is missing, corrupt or incompatible with the scene."""


class SceneError(FootageError):
    """A scene folder whose footage and calibration disagree (sizes, frame names, cameras)."""


class RunFolderBusyError(NSDError):
    """Another live run holds the run folder."""


class NonFiniteError(NSDError, FloatingPointError):
    """Training produced a NaN or infinity (a loss term, a gradient or a parameter)."""


# What a command reports as bad input (one line, exit status 2) rather than as a bug.
BAD_INPUT_ERRORS: tuple[type[Exception], ...] = (
    NSDError, FileExistsError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
    PermissionError)
