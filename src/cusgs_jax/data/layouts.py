"""``data.path`` in any of the layouts captures come in: COLMAP, Blender (NeRF-synthetic), nerfstudio.

:func:`detect_format` tells them apart by the files present; :func:`load_any_scene` loads one
into a :class:`~cusgs_jax.data.scene_data.SceneData` whose ``dataset_format`` and ``split`` say what
was read and which views were held out.

Detection (``data.format=auto``), first match wins:

1. ``transforms_train.json`` → ``"blender"`` (:mod:`.blender`);
2. ``sparse/`` (a COLMAP model, :mod:`.colmap`) → ``"colmap"`` — preferred over a
   ``transforms.json`` in the same folder, since it carries the SfM points (a log line says so;
   ``data.format=nerfstudio`` picks the other);
3. ``transforms.json`` → ``"nerfstudio"`` (:mod:`.nerfstudio`);
4. otherwise SceneError naming the folder and the three layouts.

Background (``splat.background``, None = not set): each layout has its default — white for
Blender (papers evaluate NeRF-synthetic on white), black for COLMAP and nerfstudio
(:func:`default_background`); a set colour is used as it is. The scene records the colour its
images were composited onto in ``SceneData.background``, which the run then renders on.
"""

from __future__ import annotations

import logging
import os
import pathlib

from cusgs_jax.config import DATASET_FORMATS, DataConfig
from cusgs_jax.data.blender import load_blender_scene
from cusgs_jax.data.colmap import load_scene
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.nerfstudio import load_nerfstudio_scene
from cusgs_jax.data.scene_data import SceneData

__all__ = ["DATASET_FORMATS", "detect_format", "load_any_scene", "default_background"]

log = logging.getLogger("cusgs_jax")

_BLACK = (0.0, 0.0, 0.0)
_LAYOUTS = ("a COLMAP scene (images/ and sparse/0/), a Blender / NeRF-synthetic scene (transforms_train.json "
            "and transforms_test.json) or a nerfstudio scene (transforms.json)")


def default_background(dataset_format: str) -> tuple[float, float, float]:
    """The background of a layout when ``splat.background`` is not set: white for Blender, else black."""
    return (1.0, 1.0, 1.0) if dataset_format == "blender" else _BLACK


def _folder(path) -> pathlib.Path:
    if path is None or str(path) == "":
        raise SceneError(f"data.path is empty: set it to {_LAYOUTS}")
    scene = pathlib.Path(path).expanduser()
    if not scene.exists():
        raise SceneError(f"scene folder {scene} does not exist: set data.path to {_LAYOUTS}")
    if not scene.is_dir():
        raise SceneError(f"data.path={scene} is a file, not a folder: set data.path to {_LAYOUTS}")
    return scene


def detect_format(path: str | os.PathLike) -> str:
    """``"blender"``, ``"colmap"`` or ``"nerfstudio"`` by the files in the folder ``path`` (module rules).

    Raises:
      SceneError: the folder is missing or holds none of the three layouts.
    """
    scene = _folder(path)
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
        f"{_LAYOUTS}; point data.path at such a folder, or set data.format=colmap|blender|nerfstudio to be told "
        "what that layout is missing")


def load_any_scene(path: str | os.PathLike, *, format: str = DataConfig.format, downscale: int = DataConfig.downscale,
                   holdout_every: int = DataConfig.holdout_every, background: tuple[float, float, float] | None = None,
                   num_random_points: int = DataConfig.random_points, seed: int = 0,
                   undistort: str = DataConfig.undistort, random_init: str = DataConfig.random_init) -> SceneData:
    """Load the scene folder ``path`` in its layout (``data.format``; ``"auto"``: :func:`detect_format`).

    Args:
      format: ``"auto"``, ``"colmap"``, ``"blender"`` or ``"nerfstudio"``.
      downscale, holdout_every: ``data.downscale``, ``data.holdout_every`` (Blender scenes hold out
        their test frames instead).
      background: ``splat.background``, or None for the layout's default (:func:`default_background`).
      num_random_points, seed, random_init: initial points of layouts without any (``data.random_points``,
        ``data.random_init``: :func:`cusgs_jax.data.random_points.random_points`).
      undistort: ``data.undistort``, "crop" or "mask", for distorted COLMAP and nerfstudio cameras
        (:mod:`cusgs_jax.data.undistort`).
    Returns:
      SceneData with ``dataset_format``, ``split`` and ``background`` filled in.
    Raises:
      SceneError: an unknown ``format`` or any problem with the data.
    """
    if format not in ("auto",) + DATASET_FORMATS:
        raise SceneError(f"data.format={format!r} must be auto, colmap, blender or nerfstudio")
    fmt = detect_format(path) if format == "auto" else format
    if fmt != "colmap":
        _folder(path)
    bg = default_background(fmt) if background is None else background
    if fmt == "blender":
        return load_blender_scene(path, downscale=downscale, background=bg, num_random_points=num_random_points,
                                  seed=seed, random_init=random_init)
    if fmt == "nerfstudio":
        return load_nerfstudio_scene(path, downscale=downscale, holdout_every=holdout_every, background=bg,
                                     num_random_points=num_random_points, seed=seed, undistort=undistort,
                                     random_init=random_init)

    return load_scene(path, downscale=downscale, holdout_every=holdout_every, background=bg, undistort=undistort)
