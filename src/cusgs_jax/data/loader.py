"""The one entry to a scene: :func:`load_scene` ``(path, data)`` is the scene ``cusgs-train data.path=path`` trains on.

Every caller — the trainer, feature extraction, ``cusgs-export``'s refinement, ``cusgs-render-ply``,
research code — passes a :class:`~cusgs_jax.config.DataConfig` (the run's own, or ``DataConfig()``
for the defaults ``cusgs-train`` uses), so the same settings give the same scene everywhere: the
layout is detected and read (:mod:`.layouts`: its reader gives a :class:`~cusgs_jax.data.raw.RawScene`),
then checked and finished once for every layout (:func:`cusgs_jax.data.finish.finish_scene`). The scene is in its own frame;
:func:`cusgs_jax.data.normalize.normalize_scene` moves it into the training frame.
"""

from __future__ import annotations

import os
import pathlib
from typing import NamedTuple

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo.lens import configured_demo
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import scaled_size
from cusgs_jax.data.finish import check_settings, finish_cameras, finish_scene
from cusgs_jax.data.layouts import read_scene
from cusgs_jax.data.lenses import SceneLens
from cusgs_jax.data.scene_data import SceneData

__all__ = ["SceneCameras", "load_cameras", "load_scene", "require_ssim_size", "scene_folder"]

SSIM_WINDOW = 11  # pixels per side of the SSIM window (cusgs_jax.losses.gaussian_window)


def scene_folder(path: str | os.PathLike | None, data: DataConfig, *, generate: bool = True) -> pathlib.Path:
    """The folder ``path`` names, or — when it is None or empty — the built-in demo scene of ``data.demo``
    (generated into the cache on first use when ``generate``)."""
    if path:
        return pathlib.Path(path).expanduser()
    return configured_demo(data.demo, generate=generate)


def load_scene(path: str | os.PathLike | None = None, data: DataConfig | None = None, *,
               background: tuple[float, float, float] | None = None, seed: int = 0,
               downscale_option: str = "data.downscale") -> SceneData:
    """The scene of ``path`` (default ``data.path``; neither: the built-in demo) as ``data`` loads it.

    Args:
      path: a scene folder in any layout (COLMAP, Blender, nerfstudio), or None.
      data: the settings (``format``, ``downscale``, ``holdout_every``, ``undistort``, ``random_points``,
        ``random_init``, ``demo``); None: ``DataConfig()``, the defaults ``cusgs-train`` uses.
      background: ``splat.background`` (images with alpha are composited on it), or None for the layout's.
      seed: ``train.seed``, which draws the random initial points of layouts without points.
      downscale_option: how a message names the downscale setting (a CLI's own flag, e.g. ``--downscale``).
    Returns:
      :class:`~cusgs_jax.data.scene_data.SceneData` in the scene's own frame.
    Raises:
      SceneError: anything wrong with the files or these settings, naming the file or option.
      TypeError, ValueError: a ``seed`` that is not a non-negative int (naming ``seed``).
    """
    seed = _check_seed(seed)
    data = check_settings(DataConfig() if data is None else data)
    folder = scene_folder(data.path if path is None else path, data)
    scene = finish_scene(read_scene(folder, data), data, background=background, seed=seed)
    require_ssim_size(scene, data.downscale, downscale_option)
    return scene


def _check_seed(seed) -> int:
    """``seed`` as an int: a TypeError unless it is an int (``train.seed``), a ValueError if it is negative."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be a non-negative int (train.seed, which draws the random initial points), "
                        f"got {type(seed).__name__} {seed!r}")
    if seed < 0:
        raise ValueError(f"seed must be a non-negative int (train.seed), got {seed}")
    return int(seed)


class SceneCameras(NamedTuple):
    """The cameras of a scene as :func:`load_scene` gives them (V views, in the scene's own frame).

    Attributes:
      viewmats: [V, 4, 4] float64 world→camera; Ks: [V, 3, 3] float32 at the loaded size.
      width, height: the loaded size; train_indices, test_indices: int32 split; lens: the per-view lenses
        with ``data.undistort=lens``, else None.
    """

    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int
    train_indices: np.ndarray
    test_indices: np.ndarray
    lens: SceneLens | None


def load_cameras(path: str | os.PathLike | None = None, data: DataConfig | None = None) -> SceneCameras:
    """The cameras :func:`load_scene` ``(path, data)`` would give, without reading (or undistorting) any image:
    for a tool that has a model and needs its views (an old run's training cameras, a viewer).

    Raises:
      SceneError: as :func:`load_scene`, for the files it reads and the settings.
    """
    data = check_settings(DataConfig() if data is None else data)
    raw = read_scene(scene_folder(data.path if path is None else path, data), data)
    cameras = finish_cameras(raw, data)
    return SceneCameras(raw.viewmats, cameras.Ks.astype(np.float32), cameras.width, cameras.height, cameras.train,
                        cameras.test, raw.lens)


def require_ssim_size(scene: SceneData, downscale: int, option: str) -> None:
    """SceneError unless ``scene``'s images are at least as large as the SSIM window (11×11 pixels).

    The training loss and every evaluation take the SSIM of whole images, which cannot be computed
    on images smaller than its window; ``option`` names the downscale setting in the message
    (``data.downscale`` for ``cusgs-train``, ``--downscale`` for ``cusgs-render-ply``).
    """
    k = SSIM_WINDOW
    if scene.width >= k and scene.height >= k:
        return
    if downscale > 1:
        smallest = (min(scene.width, scene.height) - 0.5) * downscale  # the full-size side is at least this
        fits = [d for d in range(1, downscale) if scaled_size(int(smallest), d) >= k]
        fix = (f"use a smaller {option} (e.g. {option}={max(fits)})" if fits
               else f"use {option}=1 (full-size images), or give it images of at least {k}x{k} pixels")
    else:
        fix = f"give it images of at least {k}x{k} pixels"
    raise SceneError(f"{scene.path}: its images load at {scene.width}x{scene.height} pixels with {option}={downscale}, "
                     f"smaller than the {k}x{k} pixels of the SSIM window that training and evaluation need; {fix}")
