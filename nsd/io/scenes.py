"""Scene folders: the one a user names, or the built-in default synthetic scene.
"""

from __future__ import annotations

from pathlib import Path

from nsd.synth import default_scene

__all__ = ["resolve_scene"]


def resolve_scene(scene: str | None) -> Path:
    """The scene folder to use: the given one, or the built-in default synthetic scene."""
    if scene:
        return Path(scene).expanduser()

    return default_scene()
