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
import pathlib

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.frames import (FrameImage, fov_focal, frame_list, frame_name, frame_path, load_frame_images,
                                   opengl_c2w_to_viewmat, read_json, require_key)
from cusgs_jax.data.images import read_image_file
from cusgs_jax.data.raw import RawScene, Split, ViewCamera

__all__ = ["read_blender", "WHITE", "TRAIN_FILE", "TEST_FILE"]

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


def read_blender(folder: pathlib.Path, data: DataConfig) -> RawScene:
    """The views of the Blender scene in ``folder`` (an existing folder) as its transforms files describe
    them: the train frames, then the test frames (its own split), with the first image's size as every
    frame's (``read_images`` checks each file has it) and the focal length of each file's field of view.

    Raises:
      SceneError: a missing/malformed JSON, key, image or matrix — naming the file and the fix.
    """
    train = _read_split(folder, folder / TRAIN_FILE, required=True)
    test = _read_split(folder, folder / TEST_FILE, required=False)
    splits = [train] + ([test] if test is not None else [])
    names = tuple(name for s in splits for name, _ in s.views)
    frames = [FrameImage(name, image, None) for s in splits for name, image in s.views]
    # the frames of both files share one size: a message about it names both files
    files = train.json_path if test is None else f"{train.json_path} and {test.json_path}"
    height, width = read_image_file(frames[0].path, "delete its frame").shape[:2]  # the full size
    cameras = tuple(ViewCamera(focal, focal, 0.5 * width, 0.5 * height, int(width), int(height))
                    for s in splits for focal in [fov_focal(width, s.angle_x)] for _ in s.views)
    num_train = len(train.views)
    split = Split(np.arange(num_train, dtype=np.int32), np.arange(num_train, len(names), dtype=np.int32),
                  "transforms_test" if len(names) > num_train else "none")
    if not len(split.test):
        log.warning("%s has no %s (or no frames in it): no held-out views; the reported PSNR will be on "
                    "training views", folder, TEST_FILE)

    loaded = {}

    def read_images(background):
        images, _, loaded["coverage"] = load_frame_images(frames, downscale=data.downscale, background=background,
                                                          json_path=train.json_path, files=files)
        return images

    return RawScene(folder=folder, dataset_format="blender", names=names,
                    viewmats=np.concatenate([s.viewmats for s in splits]), cameras=cameras, views_source=files,
                    cameras_source=train.json_path, size_fix="resize the odd ones (keep the aspect ratio)",
                    read_images=read_images, split=split, read_coverage=lambda: loaded.get("coverage"))


