"""Load a COLMAP reconstruction (cameras, poses, images, SfM points) into host NumPy arrays.

A scene folder (``data.path``) looks like the Mip-NeRF 360 / 3DGS layout::

    scene/
      images/            full-resolution images, named as in the model
      images_2/ ...      optional pre-downscaled copies (used for data.downscale=2, ...)
      sparse/0/          cameras, images, points3D (.bin or .txt; rigs/frames optional)

(``sparse/`` holding the model files directly is accepted too.)

Conventions: ``viewmats`` are world→camera 4×4 matrices with OpenCV axes (x right, y down, z
forward), i.e. COLMAP's ``cam_from_world``; ``Ks`` are pinhole intrinsics in pixels for the
loaded resolution, where the centre of the top-left pixel is (0.5, 0.5) as in COLMAP.

Camera models (:data:`SUPPORTED_CAMERA_MODELS`: those gsplat accepts, and FULL_OPENCV): PINHOLE and
SIMPLE_PINHOLE are loaded as they are; SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE and FULL_OPENCV are
kept as captured and rendered through their lens (``data.undistort=lens``, the default; :mod:`.lenses`;
FULL_OPENCV only with its rational part zero), or undistorted to PINHOLE once per scene with COLMAP's own
undistorter into the project's cache, never into the scene folder (:mod:`.undistort`: cropped with
``data.undistort=crop``, or masked with ``mask``; one common size; ``images_d/`` folders are not used, the
undistorted images are downscaled on load). A perspective model whose distortion parameters are all zero
is loaded as the pinhole it is. Any other model (FOV, THIN_PRISM_FISHEYE, ...) is refused with a
SceneError saying to run ``colmap image_undistorter``.

:func:`read_colmap` reads the model into a :class:`~cusgs_jax.data.raw.RawScene` (the shared pass,
:mod:`.finish`, checks sizes, scales the intrinsics and splits); :func:`load_scene` and
:func:`load_cameras` are that plus the pass. Every problem with the user's data raises
:class:`SceneError`, whose message names the offending file and what to do about it. The image files
are read by :mod:`.images`.
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.camera_frame import frame_cameras
from cusgs_jax.data.colmap_binary import check_binary_files
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import image_dir, load_images
from cusgs_jax.data.raw import RawScene, ViewCamera
from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.data.undistort import (
    DISTORTED_MODELS,
    PINHOLE_MODELS,
    camera_model_name,
    needs_undistortion,
    undistorted_images,
    undistorted_masks,
)

__all__ = ["SceneError", "SceneData", "read_colmap", "SUPPORTED_CAMERA_MODELS"]

SUPPORTED_CAMERA_MODELS = PINHOLE_MODELS + DISTORTED_MODELS  # the distorted ones are undistorted
_MODEL_PARTS = ("cameras", "images", "points3D")
_UNDISTORT_HINT = (
    "undistort the images first, e.g. `colmap image_undistorter --image_path <scene>/images "
    "--input_path <scene>/sparse/0 --output_path <undistorted scene> --output_type COLMAP`, "
    "and point data.path at the undistorted scene"
)
_SIZE_FIX = "undistort/crop them to a common size (e.g. `colmap image_undistorter`) and rerun"


# --------------------------------------------------------------------------------------------
# The reader, and the loaders of one COLMAP scene
# --------------------------------------------------------------------------------------------


def read_colmap(folder: pathlib.Path, data: DataConfig) -> RawScene:
    """The views of the COLMAP scene in ``folder`` (an existing folder) as its model describes them.

    Reads the model (``sparse/0`` or ``sparse``): the registered images, sorted by name, each name
    once; their cameras, of a supported model, in the frame ``data.undistort`` asks for
    (:func:`cusgs_jax.data.camera_frame.frame_cameras`); finite poses; the SfM points. The images
    (from ``images/``, ``images_{d}/`` for ``data.downscale`` d when present, or the undistorted copy in
    the cache) are read when :class:`~cusgs_jax.data.raw.RawScene` ``read_images`` is called.

    Raises:
      SceneError: anything wrong with the model files, naming the file and the fix.
    """
    model_dir = _find_model_dir(folder)
    files = _model_files(model_dir)
    rec = _read_reconstruction(model_dir, files)
    entries = _registered_images(rec, files)
    used = {}  # {camera id: pycolmap Camera} of the registered images
    for _, _, image in entries:
        if image.camera_id not in used:
            used[image.camera_id] = _check_camera_model(rec.cameras[image.camera_id],
                                                        image.camera_id, files["cameras"])
    views = [(name, image.camera_id) for name, _, image in entries]
    where = {cid: f"camera {cid} in {files['cameras']}" for cid in used}
    framed = frame_cameras(used, [cid for _, cid in views], where, [where[cid] for _, cid in views],
                           data.undistort,
                           lambda: undistorted_images(folder, model_dir, views, used, mode=data.undistort),
                           files["cameras"])
    intrinsics = {cid: _camera_intrinsics(cam, cid, files["cameras"], keep_distortion=framed.lens is not None)
                  for cid, cam in framed.cameras.items()}
    names, viewmats = _poses(entries, files)
    points, point_colors = _points(rec, files["points3D"])
    downscale = data.downscale

    def read_images(background):
        root = folder if framed.undistorted is None else framed.undistorted()
        image_folder, from_prescaled = image_dir(root, downscale)
        return load_images(image_folder, views, intrinsics, downscale, from_prescaled, folder, background=background)

    def read_valid():
        return undistorted_masks(framed.undistorted(), [cid for _, cid in views], downscale)

    cameras = tuple(ViewCamera(*(intrinsics[cid][k] for k in ("fx", "fy", "cx", "cy", "width", "height")))
                    for _, cid in views)
    return RawScene(folder=folder, dataset_format="colmap", names=tuple(names), viewmats=viewmats, cameras=cameras,
                    views_source=files["images"], cameras_source=files["cameras"], size_fix=_SIZE_FIX,
                    read_images=read_images, points=points, point_colors=point_colors,
                    read_valid=None if framed.undistorted is None else read_valid, lens=framed.lens)


# --------------------------------------------------------------------------------------------
# Views and poses
# --------------------------------------------------------------------------------------------


def _registered_images(rec, files: dict[str, pathlib.Path]) -> list[tuple[str, int, Any]]:
    """[(name, image id, pycolmap Image), ...] of the images with a pose (an image without one
    cannot be trained on), sorted by name; SceneError when there are none."""
    entries = []
    for image_id, image in rec.images.items():
        if not _has_pose(image):
            continue
        entries.append((image.name, image_id, image))
    entries.sort(key=lambda e: e[0])
    if not entries:
        raise SceneError(
            f"the COLMAP model {files['images']} has no registered images: the reconstruction "
            "failed or is empty — rerun SfM (e.g. `colmap mapper`) and point data.path at its "
            "output")
    _check_unique_names(entries, files["images"])
    return entries


def _check_unique_names(entries, images_file: pathlib.Path) -> None:
    """SceneError when two registered images of ``entries`` (sorted by name) share a name: both
    would be trained against the same image file."""
    ids_by_name: dict[str, list[int]] = {}
    for name, image_id, _ in entries:
        ids_by_name.setdefault(name, []).append(image_id)
    dups = {name: sorted(ids) for name, ids in ids_by_name.items() if len(ids) > 1}
    if not dups:
        return
    name, ids = next(iter(dups.items()))
    others = (f" (and {len(dups) - 1} more duplicated name(s): "
              f"{', '.join(repr(n) for n in list(dups)[1:4])}{', ...' if len(dups) > 4 else ''})"
              if len(dups) > 1 else "")
    raise SceneError(
        f"the COLMAP model {images_file} has {len(ids)} registered images named {name!r} (image "
        f"ids {', '.join(map(str, ids))}){others}: they would all be trained against the one "
        "file of that name, i.e. some views against another view's pixels. Every image in the "
        "model must have a unique name — delete the duplicates from the model (e.g. `colmap "
        "image_deleter`, or edit images.txt after `colmap model_converter --output_type TXT`) "
        "or rerun SfM on uniquely named images")


def _poses(entries, files: dict[str, pathlib.Path]) -> tuple[list[str], np.ndarray]:
    """Names and [V, 4, 4] float64 world→camera matrices of ``entries``; SceneError on a
    non-finite pose."""
    names, viewmats = [], []
    for name, _, image in entries:
        mat = _cam_from_world(image)
        if mat.shape != (3, 4) or not np.all(np.isfinite(mat)):
            raise SceneError(
                f"image {name!r} in {files['images']} has a non-finite pose (NaN/Inf in "
                "cam_from_world); the reconstruction is broken — rerun SfM / bundle adjustment, "
                "or delete that image from the model")
        view = np.eye(4)
        view[:3, :] = mat
        names.append(name)
        viewmats.append(view)
    return names, np.stack(viewmats)


# --------------------------------------------------------------------------------------------
# Model files
# --------------------------------------------------------------------------------------------


def _has_model_file(folder: pathlib.Path, part: str) -> bool:
    return any((folder / f"{part}{ext}").is_file() for ext in (".bin", ".txt"))


def _find_model_dir(scene: pathlib.Path) -> pathlib.Path:
    sparse = scene / "sparse"
    if (sparse / "0").is_dir():
        return sparse / "0"
    if sparse.is_dir():
        if any(_has_model_file(sparse, p) for p in _MODEL_PARTS):
            return sparse
        subdirs = sorted(p.name for p in sparse.iterdir() if p.is_dir())
        extra = (f" (it has sub-folders {', '.join(subdirs)}: move the model you want to "
                 "sparse/0/)") if subdirs else ""
        raise SceneError(
            f"no COLMAP model in {sparse}: expected the model files (cameras, images, points3D "
            f"as .bin or .txt) in {sparse / '0'} or in {sparse} itself{extra}; run COLMAP SfM "
            "(e.g. `colmap mapper`) or check data.path")
    raise SceneError(
        f"no COLMAP model folder in {scene}: expected {sparse / '0'} (or {sparse}) holding "
        "cameras, images and points3D (.bin or .txt); run COLMAP SfM (e.g. `colmap mapper`) "
        "or set data.path to the scene folder that contains sparse/")


def _model_files(model_dir: pathlib.Path) -> dict[str, pathlib.Path]:
    """The model file for each part (binary preferred, as COLMAP does); error when missing."""
    files, missing = {}, []
    for part in _MODEL_PARTS:
        for ext in (".bin", ".txt"):
            if (model_dir / f"{part}{ext}").is_file():
                files[part] = model_dir / f"{part}{ext}"
                break
        else:
            missing.append(f"{part}.bin/.txt")
    if missing:
        raise SceneError(
            f"incomplete COLMAP model in {model_dir}: missing {', '.join(missing)}; re-export "
            "the reconstruction (e.g. `colmap model_converter --output_type BIN`) or point "
            "data.path at a complete scene")
    return files


def _read_reconstruction(model_dir: pathlib.Path, files: dict[str, pathlib.Path]):
    check_binary_files(files)
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - pycolmap is a dependency
        raise SceneError("reading COLMAP scenes needs pycolmap: `pip install pycolmap`") from e
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises ValueError, RuntimeError, MemoryError, ...
        names = ", ".join(p.name for p in files.values())
        raise SceneError(
            f"pycolmap could not read the COLMAP model in {model_dir} ({names}): "
            f"{type(e).__name__}: {e}. The files are corrupt or truncated, or were written by "
            "an incompatible COLMAP version — re-export them (e.g. `colmap model_converter`) "
            "or rerun SfM") from e


def _has_pose(image) -> bool:
    for attr in ("has_pose", "registered"):  # pycolmap >= 3.12 / older
        value = getattr(image, attr, None)
        if value is not None:
            return bool(value() if callable(value) else value)
    return True


def _cam_from_world(image) -> np.ndarray:
    cfw = image.cam_from_world
    if callable(cfw):  # a method in pycolmap >= 3.12 (rigs/frames), a property before
        cfw = cfw()
    return np.asarray(cfw.matrix(), dtype=np.float64)


def _check_camera_model(camera, camera_id: int, cameras_file: pathlib.Path):
    """``camera`` (a pycolmap Camera) when its model is one of SUPPORTED_CAMERA_MODELS;
    SceneError naming the model, the camera and the file otherwise."""
    model = camera_model_name(camera)
    if model not in SUPPORTED_CAMERA_MODELS:
        raise SceneError(
            f"camera {camera_id} in {cameras_file} uses the {model} camera model, which is not "
            f"supported: the supported models are {', '.join(PINHOLE_MODELS)} and (undistorted "
            f"automatically) {', '.join(DISTORTED_MODELS)}. For any other model, "
            + _UNDISTORT_HINT)
    if model in DISTORTED_MODELS:  # checked before COLMAP undistorts with them
        params = np.asarray(camera.params, dtype=np.float64)
        focal = min(camera.focal_length_x, camera.focal_length_y)
        if (not np.all(np.isfinite(params)) or focal <= 0 or int(camera.width) <= 0
                or int(camera.height) <= 0):
            raise SceneError(
                f"camera {camera_id} in {cameras_file} has invalid parameters ({model} "
                f"{params.tolist()}, {int(camera.width)}x{int(camera.height)}); the file may be "
                "corrupt — re-export it or rerun SfM")
    return camera


def _camera_intrinsics(camera, camera_id: int, cameras_file: pathlib.Path, *, keep_distortion: bool = False) -> dict:
    """The pinhole intrinsics dict (fx, fy, cx, cy, width, height, model) of a PINHOLE or
    SIMPLE_PINHOLE camera, or of a perspective model without distortion (all its distortion
    parameters zero) — or, with ``keep_distortion`` (``data.undistort=lens``), the focal lengths and
    principal point of any distorted model; SceneError for invalid values."""
    model = camera_model_name(camera)
    params = np.asarray(camera.params, dtype=np.float64)
    if model == "PINHOLE":
        fx, fy, cx, cy = params[:4]
    elif model == "SIMPLE_PINHOLE":
        f, cx, cy = params[:3]
        fx = fy = f
    elif model in DISTORTED_MODELS and (keep_distortion or not needs_undistortion(camera)):
        fx, fy = camera.focal_length_x, camera.focal_length_y
        cx, cy = camera.principal_point_x, camera.principal_point_y
    else:  # pragma: no cover - read_colmap undistorts or refuses every other camera
        raise SceneError(
            f"camera {camera_id} in {cameras_file} uses the {model} camera model, which cannot "
            "be loaded as a pinhole camera: " + _UNDISTORT_HINT)
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        raise SceneError(
            f"camera {camera_id} in {cameras_file} has invalid intrinsics "
            f"(fx={fx}, fy={fy}, cx={cx}, cy={cy}); the file may be corrupt — re-export it or "
            "rerun SfM / undistortion")
    width, height = int(camera.width), int(camera.height)
    if width <= 0 or height <= 0:
        raise SceneError(f"camera {camera_id} in {cameras_file} has an invalid size "
                         f"{width}x{height}; rerun SfM / undistortion")
    return dict(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=width,
                height=height, model=model)


def _points(rec, points_file: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    ids = sorted(rec.points3D.keys())
    if not ids:
        raise SceneError(
            f"the reconstruction has no points: {points_file} holds 0 3D points, and training "
            "starts from the SfM point cloud — rerun SfM or point triangulation (e.g. `colmap "
            "point_triangulator`) so that points3D is filled")
    pts = rec.points3D
    xyz = np.array([pts[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([pts[i].color for i in ids]).reshape(-1, 3)
    keep = np.all(np.isfinite(xyz), axis=-1)
    if not np.any(keep):
        raise SceneError(
            f"all {len(ids)} points in {points_file} are non-finite (NaN/Inf); rerun SfM or "
            "point triangulation")
    xyz, rgb = xyz[keep], rgb[keep]
    return xyz.astype(np.float64), np.clip(rgb, 0, 255).astype(np.uint8)
