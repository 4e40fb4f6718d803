"""The error raised for problems with scene data on disk (re-exported by :mod:`.colmap`)."""

from __future__ import annotations

from cusgs_jax.errors import UserError

__all__ = ["SceneError"]


class SceneError(UserError):
    """A problem with the scene data on disk (or its settings); the message says how to fix it."""
