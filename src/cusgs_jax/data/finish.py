"""The pass every scene goes through once its layout has been read: :func:`finish_scene`.

A layout reader (:mod:`.colmap`, :mod:`.blender`, :mod:`.nerfstudio`) gives a
:class:`~cusgs_jax.data.raw.RawScene`; this module checks and completes it the same way for every
layout, in this order:

1. the settings (``data.downscale`` ≥ 1, ``data.holdout_every`` ≥ 0, ``data.random_points`` ≥ 2:
   :func:`check_settings`, before the reader runs);
2. unique view names; one common size at ``data.downscale`` (naming the file and the two views);
3. intrinsics at the loaded size (full-size ones / d) and the hold-out split (the layout's own, or
   every ``holdout_every``-th view: :func:`~cusgs_jax.data.scene_data.holdout_split`) —
   :func:`finish_cameras`, which is all a tool that reads no image needs;
4. the background (``splat.background``, or the layout's default: white for Blender, black else);
5. the images (and valid-pixel masks), read by the layout at the loaded size;
6. initial points: the layout's, or :func:`~cusgs_jax.data.random_points.random_points` of the
   training cameras by ``data.random_init``;
7. :func:`~cusgs_jax.data.scene_data.make_scene`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pathlib
from typing import NamedTuple

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import check_background, require_loadable_size, scaled_size
from cusgs_jax.data.carve import carve
from cusgs_jax.data.random_points import random_points, resolve_random_init
from cusgs_jax.data.raw import RawScene, ViewCamera
from cusgs_jax.data.scene_data import SceneData, check_int_setting, holdout_split, make_scene, split_name

__all__ = ["FinishedCameras", "LAYOUTS", "check_settings", "default_background", "existing_folder",
           "finish_cameras", "finish_scene"]

log = logging.getLogger("cusgs_jax")
MIN_CARVED = 4  # fewer random points left by carving: refused (as fewer anchors are, training/state.py)

LAYOUTS = ("a COLMAP scene (images/ and sparse/0/), a Blender / NeRF-synthetic scene (transforms_train.json "
           "and transforms_test.json) or a nerfstudio scene (transforms.json)")
_INT_SETTINGS = (("downscale", 1), ("holdout_every", 0), ("random_points", 2))


def existing_folder(path: str | os.PathLike | None) -> pathlib.Path:
    """``data.path`` as an existing folder (``~`` expanded); SceneError naming it and the layouts otherwise."""
    if path is None or str(path) == "":
        raise SceneError(f"data.path is empty: set it to {LAYOUTS}")
    scene = pathlib.Path(path).expanduser()
    if not scene.exists():
        raise SceneError(f"scene folder {scene} does not exist: set data.path to {LAYOUTS}")
    if not scene.is_dir():
        raise SceneError(f"data.path={scene} is a file, not a folder: set data.path to {LAYOUTS}")
    return scene


def default_background(dataset_format: str) -> tuple[float, float, float]:
    """The background of a layout when ``splat.background`` is not set: white for Blender (papers evaluate
    NeRF-synthetic on white), else black."""
    return (1.0, 1.0, 1.0) if dataset_format == "blender" else (0.0, 0.0, 0.0)


def check_settings(data: DataConfig) -> DataConfig:
    """``data`` with its integer settings checked (integral floats accepted); SceneError naming the option.
    A ``data`` that is not a :class:`~cusgs_jax.config.DataConfig` is a TypeError naming what to pass."""
    if not isinstance(data, DataConfig):
        hint = ("pass cfg.data, not the whole Config" if type(data).__name__ == "Config" else
                "build one with DataConfig(**settings)" if isinstance(data, dict) else "pass a DataConfig")
        raise TypeError(f"data must be a cusgs_jax.config.DataConfig, got {type(data).__name__}: {hint}")
    return dataclasses.replace(data, **{name: check_int_setting(f"data.{name}", getattr(data, name), minimum=minimum)
                                        for name, minimum in _INT_SETTINGS})


class FinishedCameras(NamedTuple):
    """The cameras of a scene at the loaded size: Ks [V, 3, 3] float64, width, height, the split."""

    Ks: np.ndarray
    width: int
    height: int
    train: np.ndarray
    test: np.ndarray
    split: str


def _check_unique_names(raw: RawScene) -> None:
    seen: set[str] = set()
    for name in raw.names:
        if name in seen:
            raise SceneError(f"two views of {raw.views_source} use the same image {name!r}: every view must have "
                             "its own image file — delete the duplicate")
        seen.add(name)


def _common_size(raw: RawScene, downscale: int) -> tuple[int, int]:
    """The loaded (W, H) every view shares at ``downscale``; SceneError naming the file and two views."""
    for width, height in {(c.width, c.height) for c in raw.cameras}:
        require_loadable_size(width, height, downscale, raw.cameras_source)
    sizes = [(scaled_size(c.width, downscale), scaled_size(c.height, downscale)) for c in raw.cameras]
    for name, size in zip(raw.names, sizes):
        if size != sizes[0]:
            raise SceneError(
                f"the images of {raw.views_source} do not share one size with data.downscale={downscale}: "
                f"{raw.names[0]!r} loads at {sizes[0][0]}x{sizes[0][1]} but {name!r} at {size[0]}x{size[1]}; all "
                f"training images must have one resolution — {raw.size_fix}")
    return sizes[0]


def _intrinsics(camera: ViewCamera, downscale: int) -> np.ndarray:
    d = float(downscale)
    return np.array([[camera.fx / d, 0.0, camera.cx / d], [0.0, camera.fy / d, camera.cy / d], [0.0, 0.0, 1.0]])


def finish_cameras(raw: RawScene, data: DataConfig) -> FinishedCameras:
    """Steps 2–3 of the module: the views' names and sizes checked, their intrinsics at the loaded
    size and the split — no image read. ``data`` as :func:`check_settings` returns it."""
    _check_unique_names(raw)
    width, height = _common_size(raw, data.downscale)
    Ks = np.stack([_intrinsics(c, data.downscale) for c in raw.cameras])
    if raw.split is not None:
        train, test, split = raw.split
    else:
        train, test = holdout_split(len(raw.names), data.holdout_every, raw.folder)
        split = split_name(data.holdout_every)
    return FinishedCameras(Ks, int(width), int(height), np.asarray(train, np.int32), np.asarray(test, np.int32), split)


def finish_scene(raw: RawScene, data: DataConfig, *, background: tuple[float, float, float] | None = None,
                 seed: int = 0) -> SceneData:
    """The :class:`~cusgs_jax.data.scene_data.SceneData` of ``raw`` (the module's steps 2–7).

    Args:
      raw: what the layout read.
      data: the settings, as :func:`check_settings` returns them.
      background: ``splat.background``, or None for the layout's (:func:`default_background`).
      seed: draws the random initial points of layouts without points (``train.seed``).
    """
    cameras = finish_cameras(raw, data)
    background = default_background(raw.dataset_format) if background is None else check_background(background)
    images = raw.read_images(background)
    valid = None if raw.read_valid is None else raw.read_valid()
    rule, carving = None, None
    if raw.points is None:
        rule = resolve_random_init(data.random_init, raw.dataset_format)
        points, colors = random_points(raw.viewmats[cameras.train], cameras.Ks[cameras.train], cameras.width,
                                       cameras.height, num=data.random_points, seed=seed, init=rule)
        log.info("%s scene %s: %d random initial points (the layout has no points; data.random_init=%s)",
                 raw.dataset_format, raw.folder, len(points), rule)
        if data.carve == "auto":
            points, colors, carving = _carved(raw, cameras, points, colors)
    else:
        points, colors = raw.points, raw.point_colors
    return make_scene(path=raw.folder, names=raw.names, images=images, viewmats=raw.viewmats, Ks=cameras.Ks,
                      points=points, point_colors=colors, train_indices=cameras.train, test_indices=cameras.test,
                      dataset_format=raw.dataset_format, split=cameras.split, background=background,
                      random_points=rule, valid=valid, lens=raw.lens, carving=carving)


def _carved(raw: RawScene, cameras: FinishedCameras, points: np.ndarray, colors: np.ndarray):
    """``points`` and ``colors`` less what no training view can hold (:func:`cusgs_jax.data.carve.carve`), and
    the :class:`~cusgs_jax.data.carve.Carving` record (``data.carve=auto``)."""
    coverage = raw.read_coverage() if raw.read_coverage is not None else None
    train = cameras.train
    keep, carving = carve(points, raw.viewmats[train], cameras.Ks[train], cameras.width, cameras.height,
                          None if coverage is None else [coverage[i] for i in train],
                          names=[raw.names[i] for i in train])
    ignored = (f"; {len(carving.ignored_views)} view(s) with blank alpha ignored: "
               f"{', '.join(carving.ignored_views)}" if carving.ignored_views else "")
    if carving.kept < min(MIN_CARVED, carving.points):
        raise SceneError(
            f"data.path={str(raw.folder)!r}: carving left {carving.kept} of {carving.points} random initial points "
            f"({carving.outside_frusta} outside every training view, {carving.transparent} voted transparent by the "
            f"{carving.views_with_alpha} views with alpha{ignored}): the cameras do not look at a common region or the "
            "images' alpha is not coverage; check the poses, or keep every point with data.carve=none")
    log.info("carved the random initial points: %d of %d kept (%d outside every training view, %d voted transparent "
             "by the views with alpha; %d of %d training views carry alpha%s; data.carve=none keeps them all)",
             carving.kept, carving.points, carving.outside_frusta, carving.transparent, carving.views_with_alpha,
             len(train), ignored)
    return points[keep], colors[keep], carving
