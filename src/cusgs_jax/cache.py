"""The project's cache folder: generated demo scenes, undistorted images, compiled XLA programs.

``$CUSGS_CACHE_DIR``, or ``~/.cache/cusgs_jax`` when it is unset; every cached thing lives below it
(``demo3-…/``, ``undistorted/``, ``xla/``), so deleting it is always safe (it is rebuilt on use).
"""

from __future__ import annotations

import os
import pathlib

__all__ = ["default_cache_dir"]


def default_cache_dir() -> pathlib.Path:
    """``$CUSGS_CACHE_DIR``, or ``~/.cache/cusgs_jax`` when unset.

    Raises:
      UserError: ``CUSGS_CACHE_DIR`` names something that is not a folder (a file).
    """
    env = os.environ.get("CUSGS_CACHE_DIR")
    folder = pathlib.Path(env) if env else pathlib.Path.home() / ".cache" / "cusgs_jax"
    if folder.exists() and not folder.is_dir():
        from cusgs_jax.errors import UserError

        where = f"CUSGS_CACHE_DIR={env}" if env else str(folder)
        raise UserError(f"{where} is not a folder (a file is there): point CUSGS_CACHE_DIR at a folder, "
                        "or unset it to use ~/.cache/cusgs_jax")
    return folder
