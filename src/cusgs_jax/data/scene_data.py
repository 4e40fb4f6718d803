"""The scene every layout loads into: :class:`SceneData`, built by :func:`make_scene` alone.

The layout modules (:mod:`.colmap`, :mod:`.blender`, :mod:`.nerfstudio`) read their files into
arrays; :func:`make_scene` is the one place a :class:`SceneData` is constructed, so what every
scene shares — dtypes, the camera extent, the background check, the split's name — is written once.

Shapes: V views, H×W images, P points.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

import numpy as np

from cusgs_jax.data.carve import Carving

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import check_background
from cusgs_jax.data.lenses import SceneLens
from cusgs_jax.data.normalize import camera_centers, camera_extent

__all__ = ["SceneData", "check_int_setting", "holdout_split", "make_scene", "split_name"]


@dataclasses.dataclass(frozen=True, eq=False)  # arrays: compare/hash by identity
class SceneData:
    """A scene loaded into host memory: what every layout (COLMAP, Blender, nerfstudio) gives the trainer.

    Attributes:
      path: the scene folder (``data.path``).
      names: image names as stored in the model, sorted.
      images: [V, H, W, 3] uint8 RGB images at the loaded resolution (any alpha channel
        composited onto ``load_scene``'s ``background``).
      viewmats: [V, 4, 4] float64 world→camera matrices (OpenCV axes, COLMAP cam_from_world; double precision
        as COLMAP stores them, since a far-off origin loses float32 precision; float32 after
        :func:`cusgs_jax.data.normalize.normalize_scene`).
      Ks: [N, 3, 3] float32 intrinsics scaled to the loaded resolution.
      width, height: the loaded resolution, shared by all images.
      points: [P, 3] float64 SfM points (sorted by COLMAP point id; float32 once normalised).
      point_colors: [P, 3] uint8 colours of those points.
      train_indices, test_indices: int32 indices into ``names``; test views are every
        ``holdout_every``-th image (``i % holdout_every == 0``), none when it is 0.
      extent: 1.1 × the largest distance of a camera centre from the mean camera centre
        (:func:`cusgs_jax.data.normalize.camera_extent`; from the points when the cameras coincide).
      dataset_format: the layout it was read from: "colmap", "blender" or "nerfstudio"
        (:mod:`cusgs_jax.data.layouts`).
      split: how the held-out views were chosen, e.g. "every_8th", "none" or
        "transforms_test" (Blender's test frames).
      background: RGB in [0, 1] that images with alpha were composited onto.
      random_points: None for SfM points (or a PLY's); for a layout without points, the rule
        (``"cube"`` or ``"cube_and_rays"``) :func:`cusgs_jax.data.random_points.random_points` drew them
        by (``eval.json``'s ``initial_points``); ``model.voxel_size=auto`` then uses
        :func:`cusgs_jax.data.random_points.random_voxel_size` instead of their spacing.
      valid: [V, H, W] bool, True where a pixel holds image content — the valid-pixel masks of
        distorted cameras undistorted with ``data.undistort=mask`` (:mod:`.undistort`); None when
        every pixel is valid. The loss, the held-out metrics and the feature targets ignore the
        others.
      lens: the per-view lens distortion the images were captured through
        (:class:`cusgs_jax.data.lenses.SceneLens`: coeffs [V, 6], bounds [V, 4], fisheye), kept with
        ``data.undistort=lens`` (:mod:`.lenses`; ``Lens.of_views`` gives one camera's); None when the
        images are pinhole images.
      carving: what carving did to the random initial points (:class:`cusgs_jax.data.carve.Carving`), or None
        (SfM points, or ``data.carve=none``).
    """

    path: pathlib.Path
    names: tuple[str, ...]
    images: np.ndarray
    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int
    points: np.ndarray
    point_colors: np.ndarray
    train_indices: np.ndarray
    test_indices: np.ndarray
    extent: float
    dataset_format: str = "colmap"
    split: str = "every_8th"
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    random_points: str | None = None
    valid: np.ndarray | None = None
    lens: SceneLens | None = None
    carving: Carving | None = None

    @property
    def camera_centers(self) -> np.ndarray:
        """[V, 3] camera centres in world coordinates (float64): -Rᵀt."""
        return camera_centers(self.viewmats)

    @property
    def num_images(self) -> int:
        return len(self.names)

    @property
    def camera_frame(self) -> str:
        """The frame the images are in, one of :data:`cusgs_jax.config.CAMERA_FRAMES` (``eval.json``'s
        ``camera_frame``, a feature set's ``undistort``): "lens" (as captured, rendered through the lens),
        "mask" (undistorted in the source frame, valid pixels only) or "crop" (pinhole images: as
        captured, or undistorted and cropped)."""
        if self.lens is not None:
            return "lens"
        return "mask" if self.valid is not None else "crop"


def split_name(holdout_every: int) -> str:
    """``SceneData.split`` for an every-N-th hold-out: "every_8th", …, or "none" for 0."""
    holdout_every = int(holdout_every)
    if holdout_every <= 0:
        return "none"
    suffix = "th" if 10 <= holdout_every % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(holdout_every % 10, "th")
    return f"every_{holdout_every}{suffix}"


def make_scene(*, path, names, images: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, points: np.ndarray,
               point_colors: np.ndarray, train_indices: np.ndarray, test_indices: np.ndarray, dataset_format: str,
               split: str, background, random_points: str | None = None, valid: np.ndarray | None = None,
               lens: SceneLens | None = None, carving: Carving | None = None) -> SceneData:
    """The :class:`SceneData` of a layout's arrays: images [V, H, W, 3] uint8 (their size is the scene's),
    viewmats [V, 4, 4] and points [P, 3] kept in float64, Ks [V, 3, 3] in float32, the extent from the cameras
    (from the points when the cameras coincide: :func:`cusgs_jax.data.normalize.camera_extent`) and the
    background checked (:func:`cusgs_jax.data.images.check_background`)."""
    viewmats = np.asarray(viewmats, np.float64)
    points = np.asarray(points, np.float64)
    extent, _ = camera_extent(camera_centers(viewmats), points)
    height, width = images.shape[1:3]
    return SceneData(path=pathlib.Path(path), names=tuple(names), images=images, viewmats=viewmats,
                     Ks=np.asarray(Ks, np.float32), width=int(width), height=int(height), points=points,
                     point_colors=np.asarray(point_colors), train_indices=np.asarray(train_indices, np.int32),
                     test_indices=np.asarray(test_indices, np.int32), extent=extent, dataset_format=dataset_format,
                     split=split, background=check_background(background), random_points=random_points,
                     valid=valid, lens=lens, carving=carving)


def holdout_split(num: int, holdout_every: int, scene: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) int32 indices into the N = ``num`` views: test = every
    ``holdout_every``-th (``i % holdout_every == 0``), none when 0; SceneError when no training
    view is left."""
    idx = np.arange(num, dtype=np.int32)
    if holdout_every > 0:
        test_mask = idx % holdout_every == 0
    else:
        test_mask = np.zeros(num, bool)
    train_indices, test_indices = idx[~test_mask], idx[test_mask]
    if train_indices.size == 0:
        raise SceneError(
            f"data.holdout_every={holdout_every} holds out all {num} image(s) of {scene}, "
            "leaving nothing to train on: set data.holdout_every=0 (no test views) or a larger "
            "value")
    return train_indices, test_indices


def check_int_setting(name: str, value: Any, *, minimum: int) -> int:
    """``value`` as an int >= ``minimum`` (integral floats accepted); SceneError otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise SceneError(f"{name}={value!r} must be an integer >= {minimum}")
    if value < minimum:
        raise SceneError(f"{name}={value} must be an integer >= {minimum}")
    return int(value)
