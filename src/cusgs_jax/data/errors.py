"""The error raised for problems with scene data on disk (re-exported by :mod:`.colmap`)."""

from __future__ import annotations

__all__ = ["SceneError"]


class SceneError(ValueError):
    """A problem with the scene data on disk (or its settings); the message says how to fix it."""
