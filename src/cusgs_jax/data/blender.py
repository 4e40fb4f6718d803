"""Load a NeRF-synthetic (Blender) scene into a :class:`~cusgs_jax.data.scene_data.SceneData`.

Layout (``data.path``)::

    scene/
      transforms_train.json   {"camera_angle_x": ..., "frames": [{"file_path": "./train/r_0",
      transforms_test.json                                         "transform_matrix": [[...] x4]}, ...]}
      transforms_val.json     (optional, ignored)
      train/ test/ val/       the images, usually RGBA PNG

* ``camera_angle_x``: the horizontal field of view in radians, per JSON file.
* ``file_path``: relative to the scene folder; ``.png`` is appended when the path as written
  does not exist (the NeRF-synthetic files name ``./train/r_0`` for ``train/r_0.png``).
* ``transform_matrix``: camera-to-world, OpenGL/Blender camera axes; converted to the project's
  world→camera OpenCV ``viewmats`` by :func:`cusgs_jax.data.frames.opengl_c2w_to_viewmat`.

Intrinsics (at full size W × H, the first image's): ``fx = fy = 0.5·W / tan(0.5·camera_angle_x)``,
``cx = W/2``, ``cy = H/2`` — the principal point at the image centre in the project's convention
(the centre of the top-left pixel is (0.5, 0.5), as in COLMAP; the original NeRF code puts pixel
centres on integers, half a pixel off Blender's true centre). ``data.downscale`` d divides them by d
and loads the images at ``round(W/d) × round(H/d)``, anti-aliased (there are no ``images_d``).

Views: the train frames, then the test frames (``names`` are the image paths relative to the
scene, e.g. ``train/r_0.png``); ``test_indices`` are the test frames — the standard protocol's
200 views — and ``data.holdout_every`` does not apply (``split = "transforms_test"``). Without a
``transforms_test.json`` there are no held-out views (``split = "none"``, with a warning).

RGBA images are composited onto ``background``, white by default (papers report NeRF-synthetic
on white). There are no points: the scene gets :func:`cusgs_jax.data.random_points.random_points`
(100 000 grey points; ``data.random_init=auto`` puts them uniformly in the cube the training cameras look at,
as 3DGS and Scaffold-GS do for NeRF-synthetic).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import pathlib

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.frames import (FrameImage, check_unique_names, fov_focal, frame_list, frame_name, frame_path,
                                   load_frame_images, opengl_c2w_to_viewmat, read_json, require_key)
from cusgs_jax.data.images import check_background
from cusgs_jax.data.scene_data import SceneData, check_int_setting, make_scene
from cusgs_jax.data.random_points import random_points, resolve_random_init

__all__ = ["load_blender_scene", "WHITE", "TRAIN_FILE", "TEST_FILE"]

log = logging.getLogger("cusgs_jax")

WHITE = (1.0, 1.0, 1.0)
TRAIN_FILE = "transforms_train.json"
TEST_FILE = "transforms_test.json"


@dataclasses.dataclass(frozen=True)
class _Split:
    """The frames of one ``transforms_*.json``: views [(name, image path)], viewmats [V, 4, 4], FoV."""

    json_path: pathlib.Path
    views: list[tuple[str, pathlib.Path]]
    viewmats: np.ndarray
    angle_x: float


def _read_split(scene: pathlib.Path, json_path: pathlib.Path, *, required: bool) -> _Split | None:
    """The frames of ``json_path``; None when it is absent and not ``required``."""
    fix = (f"{json_path.name} must hold {{\"camera_angle_x\": <radians>, \"frames\": [{{\"file_path\": ..., "
           "\"transform_matrix\": <4x4>}, ...]}} (NeRF-synthetic layout) — re-export the scene")
    if not json_path.is_file():
        if required:
            raise SceneError(f"{json_path} does not exist: a Blender (NeRF-synthetic) scene needs "
                             f"{TRAIN_FILE} (and {TEST_FILE}); set data.path to such a folder, or data.format "
                             "to the layout of this one")
        return None
    meta = read_json(json_path, fix)
    angle = require_key(meta, "camera_angle_x", "the top level", json_path, fix)
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < math.pi:
        raise SceneError(f"camera_angle_x={angle!r} in {json_path} must be the horizontal field of view in "
                         f"radians, in (0, pi); {fix}")
    frames = frame_list(meta, json_path, fix, allow_empty=not required)
    views, viewmats = [], []
    for i, frame in enumerate(frames):
        require_key(frame, "transform_matrix", f"frames[{i}]", json_path, fix)
        path = frame_path(scene, frame, i, json_path, fix)
        viewmats.append(opengl_c2w_to_viewmat(frame["transform_matrix"], f"frames[{i}]", json_path))
        views.append((frame_name(scene, path), path))
    return _Split(json_path, views, np.stack(viewmats) if viewmats else np.zeros((0, 4, 4)), float(angle))


def load_blender_scene(path: str | os.PathLike, *, downscale: int = DataConfig.downscale,
                       background: tuple[float, float, float] | None = None,
                       num_random_points: int = DataConfig.random_points, seed: int = 0,
                       random_init: str = DataConfig.random_init) -> SceneData:
    """Load a Blender / NeRF-synthetic scene folder (see the module docstring for the layout).

    Args:
      path: the folder holding ``transforms_train.json`` (``data.path``).
      downscale: integer factor d (``data.downscale``): images at round(W/d) × round(H/d), K / d.
      background: RGB in [0, 1] under the RGBA images (``splat.background``); None = white.
      num_random_points: the initial points (``data.random_points``), drawn for the training cameras by
        the rule ``random_init`` (``data.random_init``: :func:`cusgs_jax.data.random_points.random_points`;
        ``"auto"`` is ``"cube"`` here).
      seed: of the random points.

    Returns:
      SceneData with ``dataset_format="blender"``, ``split="transforms_test"`` (``"none"`` without a
      test file), float64 ``viewmats`` [V, 4, 4], float32 ``Ks`` [V, 3, 3], uint8 ``images``
      [V, H, W, 3], grey random ``points`` [num_random_points, 3].
    Raises:
      SceneError: a missing/malformed JSON, key, image or matrix — naming the file and the fix.
    """
    downscale = check_int_setting("data.downscale", downscale, minimum=1)
    num_random_points = check_int_setting("data.random_points", num_random_points, minimum=2)
    background = WHITE if background is None else check_background(background)
    scene = pathlib.Path(path).expanduser()
    if not scene.is_dir():
        raise SceneError(f"data.path={scene} is not a folder: set it to a Blender scene folder holding {TRAIN_FILE}")
    train = _read_split(scene, scene / TRAIN_FILE, required=True)
    test = _read_split(scene, scene / TEST_FILE, required=False)
    splits = [train] + ([test] if test is not None else [])
    names = [name for s in splits for name, _ in s.views]
    check_unique_names(names, train.json_path)

    frames = [FrameImage(name, image, None) for s in splits for name, image in s.views]
    # the frames of both files share one size: a message about it names both files
    files = train.json_path if test is None else f"{train.json_path} and {test.json_path}"
    images, (width, height) = load_frame_images(frames, downscale=downscale, background=background,
                                                json_path=train.json_path, files=files)
    d = float(downscale)
    Ks = np.concatenate([np.repeat(_K(width, height, s.angle_x, d)[None], len(s.views), axis=0) for s in splits])
    viewmats = np.concatenate([s.viewmats for s in splits])
    num_train = len(train.views)
    train_indices = np.arange(num_train, dtype=np.int32)
    test_indices = np.arange(num_train, len(names), dtype=np.int32)
    if test is None or not len(test_indices):
        log.warning("%s has no %s (or no frames in it): no held-out views; the reported PSNR will be on "
                    "training views", scene, TEST_FILE)
    out_w, out_h = images.shape[2], images.shape[1]
    rule = resolve_random_init(random_init, "blender")
    points, colors = random_points(viewmats[train_indices], Ks[train_indices], out_w, out_h, num=num_random_points,
                                   seed=seed, init=rule)
    log.info("Blender scene %s: %d train / %d test views at %dx%d; %d random initial points (no SfM points; "
             "data.random_init=%s)", scene, num_train, len(test_indices), out_w, out_h, len(points), rule)
    return make_scene(path=scene, names=names, images=images, viewmats=viewmats, Ks=Ks, points=points,
                      point_colors=colors, train_indices=train_indices, test_indices=test_indices,
                      dataset_format="blender", split="transforms_test" if len(test_indices) else "none",
                      background=background, random_points=rule)


def _K(width: int, height: int, angle_x: float, downscale: float) -> np.ndarray:
    """[3, 3] pinhole intrinsics of a W × H (full-size) image with horizontal FoV ``angle_x``, divided
    by ``downscale``: f = 0.5·W / tan(0.5·angle_x) for both axes, principal point at the centre."""
    f = fov_focal(width, angle_x) / downscale
    return np.array([[f, 0.0, 0.5 * width / downscale], [0.0, f, 0.5 * height / downscale], [0.0, 0.0, 1.0]])
