"""``data.path`` in any of the layouts captures come in: COLMAP, Blender (NeRF-synthetic), nerfstudio.

:func:`detect_format` tells them apart by the files present; :data:`READERS` maps each to the one
function of its module that reads its files into a :class:`~cusgs_jax.data.raw.RawScene`
(:func:`read_scene`); :func:`cusgs_jax.data.finish.finish_scene` then checks and completes every layout
the same way. Adding a layout is a module with a reader, an entry in ``READERS`` and its files here.

Detection (``data.format=auto``), first match wins:

1. ``transforms_train.json`` → ``"blender"`` (:mod:`.blender`);
2. ``sparse/`` (a COLMAP model, :mod:`.colmap`) → ``"colmap"`` — preferred over a
   ``transforms.json`` in the same folder, since it carries the SfM points (a log line says so;
   ``data.format=nerfstudio`` picks the other);
3. ``transforms.json`` → ``"nerfstudio"`` (:mod:`.nerfstudio`);
4. otherwise SceneError naming the folder and the three layouts.

Background (``splat.background``, None = not set): each layout has its default — white for
Blender (papers evaluate NeRF-synthetic on white), black for COLMAP and nerfstudio
(:func:`~cusgs_jax.data.finish.default_background`); a set colour is used as it is. The scene records the colour its
images were composited onto in ``SceneData.background``, which the run then renders on.
"""

from __future__ import annotations

import logging
import os
import pathlib
from typing import Callable

from cusgs_jax.config import DATASET_FORMATS, DataConfig
from cusgs_jax.data.blender import read_blender
from cusgs_jax.data.colmap import read_colmap
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.finish import LAYOUTS, default_background, existing_folder
from cusgs_jax.data.nerfstudio import read_nerfstudio
from cusgs_jax.data.raw import RawScene

__all__ = ["DATASET_FORMATS", "READERS", "detect_format", "default_background", "read_scene"]

log = logging.getLogger("cusgs_jax")

# data.format → the layout's reader: (existing folder, settings) -> RawScene. A fourth layout is one
# module with such a reader, one entry here and its files in detect_format.
READERS: dict[str, Callable[[pathlib.Path, DataConfig], RawScene]] = {
    "colmap": read_colmap, "blender": read_blender, "nerfstudio": read_nerfstudio}


def detect_format(path: str | os.PathLike) -> str:
    """``"blender"``, ``"colmap"`` or ``"nerfstudio"`` by the files in the folder ``path`` (module rules).

    Raises:
      SceneError: the folder is missing or holds none of the three layouts.
    """
    scene = existing_folder(path)
    blender = (scene / "transforms_train.json").is_file()
    colmap = (scene / "sparse").is_dir()
    nerfstudio = (scene / "transforms.json").is_file()
    if blender:
        return "blender"
    if colmap:
        if nerfstudio:
            log.info("%s holds both a COLMAP model (sparse/) and a nerfstudio transforms.json: reading the COLMAP "
                     "model (it has the SfM points); set data.format=nerfstudio to read transforms.json", scene)
        return "colmap"
    if nerfstudio:
        return "nerfstudio"
    found = sorted(p.name + ("/" if p.is_dir() else "") for p in scene.iterdir())[:8]
    raise SceneError(
        f"no scene layout recognised in {scene} (it holds {', '.join(found) or 'nothing'}): data.path must be "
        f"{LAYOUTS}; point data.path at such a folder, or set data.format=colmap|blender|nerfstudio to be told "
        "what that layout is missing")


def read_scene(path: str | os.PathLike, data: DataConfig) -> RawScene:
    """The folder ``path`` read by its layout's reader (``data.format``, which :class:`DataConfig` has checked;
    ``"auto"``: :func:`detect_format`)."""
    fmt = detect_format(path) if data.format == "auto" else data.format
    return READERS[fmt](existing_folder(path), data)


