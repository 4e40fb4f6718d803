"""The project's cache folder: generated demo scenes, undistorted images, compiled XLA programs.

``$CUSGS_CACHE_DIR``, or ``~/.cache/cusgs_jax`` when it is unset; every cached thing lives below it
(``demo3-…/``, ``undistorted/``, ``xla/``), so deleting it is always safe (it is rebuilt on use).
"""

from __future__ import annotations

import os
import pathlib

__all__ = ["default_cache_dir"]


def default_cache_dir() -> pathlib.Path:
    """``$CUSGS_CACHE_DIR``, or ``~/.cache/cusgs_jax`` when unset."""
    env = os.environ.get("CUSGS_CACHE_DIR")
    return pathlib.Path(env) if env else pathlib.Path.home() / ".cache" / "cusgs_jax"
