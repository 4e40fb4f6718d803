"""Load a nerfstudio scene (``transforms.json``) into a :class:`~cusgs_jax.data.scene_data.SceneData`.

Layout (``data.path``), as ``ns-process-data`` writes it::

    scene/
      transforms.json   {"camera_model": "OPENCV", "fl_x", "fl_y", "cx", "cy", "w", "h",
                         "k1", "k2", "p1", "p2", ..., "frames": [{"file_path": "images/frame_00001.png",
                         "transform_matrix": [[...] x4]}, ...], "applied_transform": [[...] x3],
                         "ply_file_path": "sparse_pc.ply"}
      images/ images_2/ ...
      sparse_pc.ply     (optional) points with colours

* Intrinsics ``fl_x fl_y cx cy w h`` (pixels, full size; the centre of the top-left pixel is
  (0.5, 0.5) as in COLMAP) and the distortion ``k1 k2 k3 k4 p1 p2`` are read from the frame when
  it has them, else from the top level. ``data.downscale`` d divides them by d; the images come
  from ``images_{d}/<file name>`` when that file exists (nerfstudio's convention), else from
  ``file_path`` reduced with the anti-aliased filter. All frames must load at one size.
* ``camera_model`` (top level or per frame, default ``OPENCV``): perspective cameras
  (``OPENCV``, ``PINHOLE``, ``SIMPLE_PINHOLE``) with every distortion coefficient zero or absent
  load directly. Frames with lens distortion — ``OPENCV`` with non-zero ``k1 k2 k3 p1 p2`` (COLMAP's
  OPENCV model, or FULL_OPENCV with its rational part zero when ``k3`` is set) or ``OPENCV_FISHEYE`` with
  ``k1 k2 k3 k4`` — load as distorted COLMAP scenes do (``data.undistort``): kept as captured and rendered
  through their lens (:mod:`cusgs_jax.data.lenses`, the default), or undistorted to pinhole
  (:mod:`cusgs_jax.data.undistort`: COLMAP's undistorter, cached outside the scene, cropped or masked,
  ``images_{d}/`` not used; the frames' cameras are written as a temporary COLMAP model for it, so their
  images must lie under ``images/``). ``OPENCV`` with non-zero ``k4`` (nerfstudio's r⁸ term), a fisheye
  with ``p1``/``p2``, ``EQUIRECTANGULAR`` and nerfstudio's other models raise :class:`SceneError` saying
  what to do.
* ``transform_matrix``: camera-to-world with OpenGL camera axes (as Blender), converted by
  :func:`cusgs_jax.data.frames.opengl_c2w_to_viewmat`.
* ``applied_transform`` (3×4) is informational: it records the transform ``ns-process-data``
  already applied to the COLMAP poses (and to the PLY), so the poses and points are used as they
  are and it is **not** applied again.
* ``ply_file_path`` (relative to the scene folder): initial points and colours (read with
  ``plyfile``: vertex ``x y z`` and, when present, ``red green blue``). Without it the scene gets
  :func:`cusgs_jax.data.random_points.random_points` (``data.random_init=auto``: half in the cube the
  training cameras look at, half along their rays — a real capture has walls or a background around them).

Views are sorted by ``file_path``; the held-out views are every ``holdout_every``-th of them
(``i % holdout_every == 0``, the COLMAP loader's rule; 0: none), ``split = "every_8th"`` etc.
nerfstudio's own ``train_filenames`` / ``test_filenames`` lists, if present, are not used.
Images with alpha are composited onto ``background`` (black by default).
"""

from __future__ import annotations

import functools
import logging
import math
import pathlib
from typing import NamedTuple

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.camera_frame import frame_cameras
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.frames import (FrameImage, frame_list, frame_name, frame_path, load_frame_images,
                                   opengl_c2w_to_viewmat, read_json, require_key)
from cusgs_jax.data.raw import RawScene, ViewCamera
from cusgs_jax.data.undistort import undistorted_images, undistorted_masks

__all__ = ["read_nerfstudio", "TRANSFORMS_FILE", "PINHOLE_MODELS", "FISHEYE_MODEL",
           "UNSUPPORTED_MODELS"]

log = logging.getLogger("cusgs_jax")

TRANSFORMS_FILE = "transforms.json"
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")  # perspective: pinhole once the distortion is zero
FISHEYE_MODEL = "OPENCV_FISHEYE"  # undistorted with its k1..k4 (COLMAP's OPENCV_FISHEYE)
UNSUPPORTED_MODELS = ("EQUIRECTANGULAR", "FISHEYE624", "OMNIDIRECTIONALSTEREO_L",
                      "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_FIX = (f"{TRANSFORMS_FILE} must hold fl_x, fl_y, cx, cy, w, h (top level or per frame) and \"frames\": "
        "[{\"file_path\": ..., \"transform_matrix\": <4x4>}, ...] (nerfstudio layout) — re-export it, e.g. with "
        "`ns-process-data`")
_UNDISTORT_HINT = (
    "the COLMAP loader reads more camera models: when ns-process-data left its COLMAP model in "
    "<scene>/colmap/sparse/0, link it as <scene>/sparse (`ln -s colmap/sparse <scene>/sparse`) and set "
    "data.format=colmap; otherwise undistort the images first (e.g. `colmap image_undistorter --output_type "
    "COLMAP`) and point data.path at the result")
_PANORAMA_HINT = (
    "panoramas cannot be undistorted into one pinhole image: cut them into perspective views first, e.g. "
    "`ns-process-data images --camera-type equirectangular --images-per-equirect 8 --data <panoramas> "
    "--output-dir <scene>`, and point data.path at that scene")


class FrameCamera(NamedTuple):
    """A frame's camera at full size: model, pinhole part (pixels), size and distortion coefficients."""

    model: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: dict  # {k1, k2, k3, k4, p1, p2: value} of the keys present


def _number(value, key: str, where: str, json_path: pathlib.Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneError(f"{key}={value!r} ({where}) in {json_path} must be a finite number; {_FIX}")
    return float(value)


def _frame_camera(meta: dict, frame: dict, index: int, json_path: pathlib.Path) -> FrameCamera:
    """The camera of ``frames[index]`` (frame keys override the top level); SceneError on missing or
    invalid intrinsics and an unknown ``camera_model``."""
    def get(key):
        return frame[key] if key in frame else meta.get(key)

    missing = [k for k in _INTRINSIC_KEYS if get(k) is None]
    if missing:
        raise SceneError(f"frames[{index}] of {json_path} has no {', '.join(missing)} (neither in the frame nor at "
                         f"the top level); {_FIX}")
    where = f"frames[{index}]"
    fx, fy, cx, cy, w, h = (_number(get(k), k, where, json_path) for k in _INTRINSIC_KEYS)
    if fx <= 0 or fy <= 0 or w < 1 or h < 1 or w != int(w) or h != int(h):
        raise SceneError(f"{where} of {json_path} has invalid intrinsics (fl_x={fx}, fl_y={fy}, w={w}, h={h}): "
                         f"focal lengths must be > 0 and w, h whole numbers of pixels; {_FIX}")
    model = get("camera_model") or "OPENCV"
    known = PINHOLE_MODELS + (FISHEYE_MODEL,) + UNSUPPORTED_MODELS
    if not isinstance(model, str) or model not in known:
        raise SceneError(f"unknown camera_model {model!r} in {json_path} ({where}): nerfstudio's models are "
                         f"{', '.join(known)}; perspective scenes use OPENCV — "
                         "correct camera_model")
    distortion = {k: _number(get(k), k, where, json_path) for k in DISTORTION_KEYS if get(k) is not None}
    return FrameCamera(model, fx, fy, cx, cy, int(w), int(h), distortion)


def _colmap_camera(camera: FrameCamera, camera_id: int, name: str, json_path: pathlib.Path):
    """The pycolmap Camera of a frame's camera (PINHOLE, OPENCV, FULL_OPENCV for an OPENCV frame with k3 — its
    rational part zero, so the radial polynomial is nerfstudio's 1 + k1 r² + k2 r⁴ + k3 r⁶ — or OPENCV_FISHEYE),
    or SceneError for a model or distortion coefficient COLMAP's matching model does not have (k4 of a
    perspective frame: nerfstudio's r⁸ term; p1, p2 of a fisheye)."""
    import pycolmap

    if camera.model in UNSUPPORTED_MODELS:
        hint = _UNDISTORT_HINT if camera.model == "FISHEYE624" else _PANORAMA_HINT
        raise SceneError(f"frame {name!r} of {json_path} uses camera_model {camera.model}, but only perspective "
                         f"(OPENCV, PINHOLE, SIMPLE_PINHOLE) and OPENCV_FISHEYE cameras are supported; {hint}")
    coeff = {k: camera.distortion.get(k, 0.0) for k in DISTORTION_KEYS}
    extra = ("p1", "p2") if camera.model == FISHEYE_MODEL else ("k4",)
    stray = {k: coeff[k] for k in extra if coeff[k] != 0.0}
    if stray:
        values = ", ".join(f"{k}={v:g}" for k, v in stray.items())
        raise SceneError(f"frame {name!r} of {json_path} (camera_model {camera.model}) has {values}, which COLMAP's "
                         f"{camera.model} model does not have, so it cannot be undistorted here; {_UNDISTORT_HINT}")
    pinhole = [camera.fx, camera.fy, camera.cx, camera.cy]
    if camera.model == FISHEYE_MODEL:
        model, params = "OPENCV_FISHEYE", pinhole + [coeff[k] for k in ("k1", "k2", "k3", "k4")]
    elif coeff["k3"] != 0.0:
        model, params = "FULL_OPENCV", pinhole + [coeff[k] for k in ("k1", "k2", "p1", "p2", "k3")] + [0.0, 0.0, 0.0]
    elif any(coeff[k] != 0.0 for k in ("k1", "k2", "p1", "p2")):
        model, params = "OPENCV", pinhole + [coeff[k] for k in ("k1", "k2", "p1", "p2")]
    else:
        model, params = "PINHOLE", pinhole
    return pycolmap.Camera(camera_id=camera_id, model=model, width=camera.width, height=camera.height,
                           params=params)


def _under_images(scene: pathlib.Path, frames: list, json_path: pathlib.Path) -> list[str]:
    """The frames' image paths relative to ``scene/images`` (COLMAP's undistorter reads them from there);
    SceneError for a frame outside it."""
    images_dir, names = scene / "images", []
    for name, image, _ in frames:
        try:
            names.append(image.resolve().relative_to(images_dir.resolve()).as_posix())
        except ValueError:
            raise SceneError(f"frame {name!r} of {json_path} is distorted and lies outside {images_dir}: COLMAP's "
                             "undistorter reads the images of a scene from its images/ folder; move the frames "
                             "there and correct their file_path") from None
    return names


def _undistorted_folder(scene: pathlib.Path, names: list[str], views: list[int], cameras: dict,
                        mode: str) -> pathlib.Path:
    """:func:`cusgs_jax.data.undistort.undistorted_images` of the frames (``names`` under ``scene/images``), their
    cameras written as a temporary COLMAP model for it."""
    import tempfile

    import pycolmap

    model = pycolmap.Reconstruction()
    for camera in cameras.values():
        model.add_camera_with_trivial_rig(camera)
    for index, (name, cid) in enumerate(zip(names, views)):
        model.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cid, image_id=index + 1),
                                           pycolmap.Rigid3d())
    with tempfile.TemporaryDirectory(prefix="cusgs-nerfstudio-model-") as model_dir:
        model.write(model_dir)
        return undistorted_images(scene, pathlib.Path(model_dir), list(zip(names, views)), cameras, mode=mode)


def _points(scene: pathlib.Path, meta: dict, json_path: pathlib.Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(points [P, 3] float64, colours [P, 3] uint8) of ``ply_file_path``, or None when there is none.

    Colours default to mid-grey when the PLY has no ``red green blue``; non-finite points are dropped.
    """
    rel = meta.get("ply_file_path")
    if rel is None:
        return None
    fix = f"correct or remove \"ply_file_path\" in {json_path} (without it training starts from random points)"
    if not isinstance(rel, str) or not rel:
        raise SceneError(f"ply_file_path={rel!r} in {json_path} must be a file name; {fix}")
    path = scene / rel
    if not path.is_file():
        raise SceneError(f"{json_path} names the point cloud {rel!r}, but {path} does not exist; {fix}")
    try:
        from plyfile import PlyData

        vertex = PlyData.read(str(path))["vertex"].data
        xyz = np.stack([np.asarray(vertex[c], np.float64) for c in "xyz"], axis=-1).reshape(-1, 3)
        names = vertex.dtype.names or ()
        if all(c in names for c in ("red", "green", "blue")):
            rgb = np.stack([np.asarray(vertex[c], np.float64) for c in ("red", "green", "blue")], axis=-1)
        else:
            rgb = np.full(xyz.shape, 128.0)
    except Exception as e:  # plyfile raises PlyParseError, KeyError, ValueError, ...
        raise SceneError(f"cannot read the points of {path} ({type(e).__name__}: {e}): it must be a PLY with a "
                         f"vertex element holding x, y, z; {fix}") from e
    keep = np.all(np.isfinite(xyz), axis=-1)
    if not np.any(keep):
        raise SceneError(f"{path} has no finite points; {fix}")
    if not np.all(keep):
        log.warning("%s: %d of its %d points have a non-finite coordinate (NaN or Inf) and were left out", path,
                    int(np.sum(~keep)), len(keep))
    rgb = np.clip(np.nan_to_num(rgb[keep]), 0, 255).round().astype(np.uint8)
    return xyz[keep], rgb.reshape(-1, 3)


def read_nerfstudio(folder: pathlib.Path, data: DataConfig) -> RawScene:
    """The views of the nerfstudio scene in ``folder`` (an existing folder) as its ``transforms.json``
    describes them, sorted by ``file_path``, their cameras in the frame ``data.undistort`` asks for
    (:func:`cusgs_jax.data.camera_frame.frame_cameras`), with the points of its ``ply_file_path`` (or none).

    Raises:
      SceneError: malformed JSON, missing keys, a missing image, a bad matrix, an unsupported or unknown
        camera model, distortion COLMAP cannot undistort — naming the file and the fix.
    """
    json_path = folder / TRANSFORMS_FILE
    if not json_path.is_file():
        raise SceneError(f"{json_path} does not exist: a nerfstudio scene needs it; set data.path to such a "
                         "folder, or data.format to the layout of this one")
    meta = read_json(json_path, _FIX)
    frames = frame_list(meta, json_path, _FIX)
    for i, frame in enumerate(frames):
        require_key(frame, "file_path", f"frames[{i}]", json_path, _FIX)
        require_key(frame, "transform_matrix", f"frames[{i}]", json_path, _FIX)
    order = sorted(range(len(frames)), key=lambda i: str(frames[i]["file_path"]))
    frames_in, viewmats = [], []  # [(name, image path, FrameCamera)] in view order
    for i in order:
        image = frame_path(folder, frames[i], i, json_path, _FIX)
        frames_in.append((frame_name(folder, image), image, _frame_camera(meta, frames[i], i, json_path)))
        viewmats.append(opengl_c2w_to_viewmat(frames[i]["transform_matrix"], f"frames[{i}]", json_path))
    names = tuple(name for name, _, _ in frames_in)

    ids, cameras, views = {}, {}, []  # one pycolmap camera per distinct frame camera
    for name, _, camera in frames_in:
        key = (camera.model, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
               tuple(sorted(camera.distortion.items())))
        if key not in ids:
            ids[key] = len(ids) + 1
            cameras[ids[key]] = _colmap_camera(camera, ids[key], name, json_path)
        views.append(ids[key])
    first_frame = {cid: name for name, cid in zip(reversed(names), reversed(views))}
    mode, downscale = data.undistort, data.downscale
    under_images = functools.cache(lambda: _under_images(folder, frames_in, json_path))  # only when undistorting
    framed = frame_cameras(cameras, views, {cid: f"frame {first_frame[cid]!r} of {json_path}" for cid in cameras},
                           [f"frame {name!r} of {json_path}" for name in names], mode,
                           lambda: _undistorted_folder(folder, under_images(), views, cameras, mode), json_path)
    if framed.undistorted is None:  # as captured (pinhole, or a lens kept: its pinhole part)
        view_cameras = tuple(ViewCamera(c.fx, c.fy, c.cx, c.cy, c.width, c.height) for _, _, c in frames_in)
    else:  # undistorted PINHOLE cameras of one common size
        view_cameras = tuple(ViewCamera(*(float(v) for v in framed.cameras[cid].params),
                                        int(framed.cameras[cid].width), int(framed.cameras[cid].height))
                             for cid in views)

    coverage = {}  # each view's alpha coverage, once read_images has read them (carving)

    def read_images(background):
        if framed.undistorted is None:  # images_{d}/<file name> when present (nerfstudio's convention)
            images = []
            for (name, image, _), camera in zip(frames_in, view_cameras):
                prescaled = folder / f"images_{downscale}" / image.name
                use_prescaled = downscale > 1 and prescaled.is_file()
                images.append(FrameImage(name, prescaled if use_prescaled else image, (camera.width, camera.height),
                                         use_prescaled))
        else:
            undistorted = framed.undistorted() / "images"
            images = [FrameImage(name, undistorted / rel, (camera.width, camera.height), False)
                      for name, rel, camera in zip(names, under_images(), view_cameras)]
        images, _, coverage["views"] = load_frame_images(images, downscale=downscale, background=background,
                                                         json_path=json_path)
        return images

    def read_valid():
        return undistorted_masks(framed.undistorted(), views, downscale)

    loaded = _points(folder, meta, json_path)
    return RawScene(folder=folder, dataset_format="nerfstudio", names=names, viewmats=np.stack(viewmats),
                    cameras=view_cameras, views_source=json_path, cameras_source=json_path,
                    size_fix="resize/crop them to a common size (and w, h, fl_x, fl_y, cx, cy with them)",
                    read_images=read_images, points=None if loaded is None else loaded[0],
                    point_colors=None if loaded is None else loaded[1],
                    read_valid=None if framed.undistorted is None else read_valid, lens=framed.lens,
                    read_coverage=lambda: coverage.get("views"))


