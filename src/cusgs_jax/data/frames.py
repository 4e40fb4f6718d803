"""What the ``transforms*.json`` layouts (Blender / NeRF-synthetic, nerfstudio) share.

Reading the JSON, its poses and its frame images, with every problem raised as a
:class:`~cusgs_jax.data.errors.SceneError` naming the JSON file (and frame) at fault and the fix.

Pose convention of these files: ``transform_matrix`` is a camera-to-world matrix with
OpenGL/Blender camera axes (x right, y up, the camera looks along −z). The project's
``viewmats`` are world→camera with OpenCV axes (x right, y down, z forward), so
:func:`opengl_c2w_to_viewmat` flips the camera's y and z axes (``c2w[:3, 1:3] *= -1``) and
inverts the rigid transform.

Images are read with imageio; an alpha channel is composited onto the background exactly as
for COLMAP scenes (:mod:`cusgs_jax.data.images`), and downscaling uses the same anti-aliased
filter.
"""

from __future__ import annotations

import json
import math
import pathlib
from typing import Any, NamedTuple, Sequence

import numpy as np

from cusgs_jax.data.carve import coverage_at

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import (downscale_image, to_rgb_uint8, warn_alpha, read_image_file, require_loadable_size,
                                   scaled_size)

__all__ = ["FrameImage", "read_json", "require_key", "frame_list", "frame_path", "frame_name",
           "opengl_c2w_to_viewmat", "load_frame_images", "fov_focal"]

_RIGID_TOL = 1e-3  # |RᵀR − I| above this: not a rotation (scale or shear in the matrix)


def read_json(path: pathlib.Path, fix: str) -> dict:
    """The top-level object of the JSON file ``path``; SceneError (ending in ``fix``) when it is
    missing, unreadable, not JSON or not an object."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as e:
        raise SceneError(f"{path} does not exist; {fix}") from e
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"cannot read {path} ({type(e).__name__}: {e}); {fix}") from e
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise SceneError(f"{path} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg}); {fix}") from e
    if not isinstance(meta, dict):
        raise SceneError(f"{path} holds a JSON {type(meta).__name__}, not an object with \"frames\"; {fix}")
    return meta


def require_key(obj: dict, key: str, where: str, path: pathlib.Path, fix: str) -> Any:
    """``obj[key]``; SceneError "``where`` in ``path`` has no ``key``; ``fix``" when it is absent."""
    if key not in obj:
        raise SceneError(f"{where} in {path} has no \"{key}\" key; {fix}")
    return obj[key]


def frame_list(meta: dict, path: pathlib.Path, fix: str, *, allow_empty: bool = False) -> list[dict]:
    """``meta["frames"]`` checked to be a list of objects (non-empty unless ``allow_empty``)."""
    frames = require_key(meta, "frames", "the top level", path, fix)
    if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
        raise SceneError(f"\"frames\" in {path} must be a list of objects (one per image); {fix}")
    if not frames and not allow_empty:
        raise SceneError(f"\"frames\" in {path} is empty: there is no image to train on; {fix}")
    return frames


def frame_path(scene: pathlib.Path, frame: dict, index: int, json_path: pathlib.Path, fix: str) -> pathlib.Path:
    """The image file of ``frames[index]``: ``file_path`` relative to ``scene`` (absolute paths are
    kept); when that file does not exist, the same path with ``.png`` appended (Blender's
    ``"./train/r_0"`` means ``train/r_0.png``). SceneError when neither exists."""
    file_path = require_key(frame, "file_path", f"frames[{index}]", json_path, fix)
    if not isinstance(file_path, str) or not file_path:
        raise SceneError(f"frames[{index}].file_path in {json_path} must be a non-empty string, not "
                         f"{file_path!r}; {fix}")
    path = scene / file_path
    if path.is_file():
        return path
    with_png = path.with_name(path.name + ".png")
    if with_png.is_file():
        return with_png
    tried = f"{path}" + ("" if path.suffix else f" (nor {with_png})")
    raise SceneError(
        f"frames[{index}] of {json_path} names the image {file_path!r}, but {tried} does not exist: copy the "
        f"image there, correct frames[{index}].file_path, or delete that frame from {json_path.name}")


def frame_name(scene: pathlib.Path, image: pathlib.Path) -> str:
    """A view's name: the image path relative to ``scene`` in POSIX form (``train/r_0.png``), or
    the absolute path for an image outside it."""
    try:
        return image.relative_to(scene).as_posix()
    except ValueError:
        return image.as_posix()


def opengl_c2w_to_viewmat(matrix: Any, where: str, json_path: pathlib.Path) -> np.ndarray:
    """[4, 4] float64 world→camera (OpenCV axes) from a camera-to-world ``transform_matrix`` with
    OpenGL/Blender camera axes.

    Accepts a 4×4 matrix (last row 0 0 0 1) or its top 3×4. The rotation must be orthonormal
    with determinant +1 (within 1e-3; it is snapped to the nearest rotation so that
    ``camera_centers = −Rᵀt`` is exact). Conversion: ``c2w[:3, 1:3] *= −1`` (y up → y down,
    −z forward → z forward), then the rigid inverse ``[Rᵀ | −Rᵀt]``.

    Raises:
      SceneError: wrong shape, NaN/Inf, or not a rigid transform — naming ``where`` in ``json_path``.
    """
    fix = f"re-export {json_path.name} or delete that frame"
    try:
        c2w = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        c2w = None
    if c2w is None or c2w.shape not in ((4, 4), (3, 4)):
        shape = "not a matrix" if c2w is None else f"shape {c2w.shape}"
        raise SceneError(f"{where}.transform_matrix in {json_path} has {shape}; expected a 4x4 "
                         f"camera-to-world matrix (rows of 4 numbers); {fix}")
    if not np.all(np.isfinite(c2w)):
        raise SceneError(f"{where}.transform_matrix in {json_path} contains NaN or Inf; {fix}")
    if c2w.shape == (4, 4) and not np.allclose(c2w[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise SceneError(f"{where}.transform_matrix in {json_path} has last row {c2w[3].tolist()}, not "
                         f"[0, 0, 0, 1]: it is not a camera-to-world pose; {fix}")
    rot, trans = c2w[:3, :3].copy(), c2w[:3, 3]
    if np.max(np.abs(rot.T @ rot - np.eye(3))) > _RIGID_TOL or np.linalg.det(rot) <= 0:
        raise SceneError(f"{where}.transform_matrix in {json_path} is not a rigid camera pose (its 3x3 part "
                         "is not a rotation: scaled, sheared or mirrored); scale the scene through the "
                         f"translations only; {fix}")
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt  # the nearest rotation (the identity change for an exact one)
    rot[:, 1:3] *= -1.0  # OpenGL camera axes → OpenCV
    view = np.eye(4)
    view[:3, :3] = rot.T
    view[:3, 3] = -rot.T @ trans
    return view


class FrameImage(NamedTuple):
    """One image to load.

    Attributes:
      name: the view's name (for messages).
      path: the file.
      size: (w, h) the file must have (±1 px), or None: that of the first image, exactly.
      prescaled: the file is already ``downscale`` times smaller (no further resizing).
    """

    name: str
    path: pathlib.Path
    size: tuple[int, int] | None
    prescaled: bool = False


def _read(path: pathlib.Path, background) -> tuple[np.ndarray, np.ndarray | None]:
    return to_rgb_uint8(read_image_file(path, "delete its frame"), path, background)


def load_frame_images(frames: Sequence[FrameImage], *, downscale: int, background: tuple[float, float, float],
                      json_path: pathlib.Path, files: str | None = None
                      ) -> tuple[np.ndarray, tuple[int, int], list[np.ndarray | None]]:
    """Read, composite and downscale the images of ``frames``.

    Each file must have its ``size`` (±1 px, like COLMAP scenes), or — with ``size`` None — exactly
    the size of the first file. The loaded size is the full size / ``downscale`` rounded half up
    (:func:`~cusgs_jax.data.images.scaled_size`); files not ``prescaled`` are reduced to it with
    the anti-aliased filter. An alpha channel is composited onto ``background`` (RGB in [0, 1]),
    with one warning per scene.

    Returns:
      (images [V, H, W, 3] uint8, (W0, H0) the full size: the first frame's ``size``, or its file's,
      coverage: per frame [H, W] bool (alpha > 0 at the loaded size, :func:`cusgs_jax.data.carve.coverage_at`)
      or None for a file without alpha).
    Raises:
      SceneError: unreadable file, wrong or differing sizes (naming ``json_path`` — or ``files``, the
        transforms files the frames come from, when there are several — and both images).
    """
    images, full = None, None
    with_alpha, transparent, coverage = [], 0, []
    for i, frame in enumerate(frames):
        img, alpha = _read(frame.path, background)
        h, w = img.shape[:2]
        if full is None:
            full = frame.size if frame.size is not None else (w, h)
            require_loadable_size(full[0], full[1], downscale, json_path)
        expected = frame.size if frame.size is not None else full
        file_scale = downscale if frame.prescaled else 1
        exp_w, exp_h = scaled_size(expected[0], file_scale), scaled_size(expected[1], file_scale)
        tol = 1 if frame.size is not None else 0
        if abs(w - exp_w) > tol or abs(h - exp_h) > tol:
            if frame.size is None:
                raise SceneError(
                    f"the images of {files or json_path} do not share one size: {frames[0].name!r} is {full[0]}x{full[1]} "
                    f"but {frame.name!r} ({frame.path}) is {w}x{h}; all frames must have one resolution — "
                    "resize the odd ones (the field of view is per file, so keep the aspect ratio)")
            what = f"{downscale}x downscaled from {expected[0]}x{expected[1]}" if frame.prescaled else "its w, h"
            raise SceneError(
                f"image {frame.path} of frame {frame.name!r} is {w}x{h} but {json_path} says it should be "
                f"{exp_w}x{exp_h} ({what}, ±1 px): use the images the transforms were made for, or correct "
                "w and h in the JSON")
        out_hw = (scaled_size(expected[1], downscale), scaled_size(expected[0], downscale))
        if not frame.prescaled and downscale > 1:
            img = downscale_image(img, downscale, out_hw)
        if alpha is not None:
            with_alpha.append(frame.name)
            transparent += bool(np.any(alpha < 1.0))
        coverage.append(None if alpha is None else coverage_at(alpha, out_hw))
        if images is None:
            images = np.empty((len(frames),) + img.shape, np.uint8)
        elif img.shape != images.shape[1:]:
            (h0, w0), (h1, w1) = images.shape[1:3], img.shape[:2]
            raise SceneError(
                f"the frames of {json_path} do not load at one size with data.downscale={downscale}: "
                f"{frames[0].name!r} loads at {w0}x{h0} but {frame.name!r} at {w1}x{h1}; all training images "
                "must have one resolution — resize/crop them to a common size (and their intrinsics with them)")
        images[i] = img
    assert images is not None and full is not None
    if with_alpha:
        warn_alpha(json_path.parent, with_alpha, transparent, len(frames), background)
    return images, (int(full[0]), int(full[1])), coverage


def fov_focal(width: int, angle: float) -> float:
    """Focal length in pixels of a ``width``-pixel image with horizontal field of view ``angle``
    (radians): ``0.5·W / tan(0.5·angle)``."""
    return 0.5 * width / math.tan(0.5 * angle)
