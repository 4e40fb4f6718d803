"""What a layout reader hands over: :class:`RawScene`, the views as its files describe them.

A layout module (:mod:`.colmap`, :mod:`.blender`, :mod:`.nerfstudio`) parses its files into a
``RawScene`` — names, poses, full-size cameras, points when it has any, its own split when it has
one, and functions that read the images (and valid-pixel masks) when asked — and checks only what
parsing its own files needs. Everything scenes share (settings, unique names, one common size,
intrinsics at the loaded size, the hold-out split, the background, random points) is done once, by
:func:`cusgs_jax.data.finish.finish_scene`.

Shapes: V views, H×W loaded images.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Callable, NamedTuple

import numpy as np

from cusgs_jax.data.lenses import SceneLens

__all__ = ["RawScene", "Split", "ViewCamera"]


class ViewCamera(NamedTuple):
    """A view's pinhole part at full size, in pixels (the centre of the top-left pixel is (0.5, 0.5)).

    For a distorted camera kept as captured (``data.undistort=lens``) this is its focal lengths and
    principal point (the distortion lives in :class:`RawScene` ``lens``); undistorted to pinhole,
    the undistorted camera's.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


class Split(NamedTuple):
    """A layout's own hold-out (Blender's test frames): int32 indices into the views and its name."""

    train: np.ndarray
    test: np.ndarray
    name: str


@dataclasses.dataclass(frozen=True, eq=False)  # arrays: compare by identity
class RawScene:
    """One scene as its layout's files describe it, before the shared pass.

    Attributes:
      folder: the scene folder.
      dataset_format: "colmap", "blender" or "nerfstudio".
      names: [V] view names (image paths as the files give them), in view order.
      viewmats: [V, 4, 4] float64 world→camera, OpenCV axes.
      cameras: [V] :class:`ViewCamera` at full size.
      views_source: the file that lists the views (``images.bin``, ``transforms.json``), named in
        messages about names and sizes.
      cameras_source: the file that gives their sizes (``cameras.bin``, the transforms file).
      size_fix: the layout's advice when the views do not share one size.
      read_images: ``(background) -> [V, H, W, 3] uint8``, the images at the loaded size
        (``data.downscale``), alpha composited onto ``background``; raises SceneError for a missing,
        unreadable or wrongly sized file.
      points, point_colors: [P, 3] float64 points and [P, 3] uint8 colours, or None when the layout
        has none (the shared pass draws random ones).
      split: the layout's own hold-out, or None (``data.holdout_every`` applies).
      read_valid: ``() -> [V, H, W] bool | None``, the valid-pixel masks of undistorted images
        (``data.undistort=mask``), or None.
      lens: the per-view lenses of distorted cameras kept as captured (``data.undistort=lens``).
      read_coverage: ``() -> [V] of [H, W] bool | None`` after ``read_images``: each view's alpha coverage
        at the loaded size (None for a view without alpha), what carving uses (:mod:`cusgs_jax.data.carve`);
        None when the layout has no alpha.
    """

    folder: pathlib.Path
    dataset_format: str
    names: tuple[str, ...]
    viewmats: np.ndarray
    cameras: tuple[ViewCamera, ...]
    views_source: pathlib.Path | str
    cameras_source: pathlib.Path | str
    size_fix: str
    read_images: Callable[[tuple[float, float, float]], np.ndarray]
    points: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    split: Split | None = None
    read_valid: Callable[[], np.ndarray | None] | None = None
    lens: SceneLens | None = None
    read_coverage: Callable[[], list | None] | None = None
