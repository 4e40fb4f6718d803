"""Undistorting COLMAP scenes whose cameras have lens distortion, once per scene, into the cache.

:func:`cusgs_jax.data.loader.load_scene` with ``data.undistort=crop`` or ``mask`` trains on pinhole cameras
(``lens`` renders through the lens instead: :mod:`.lenses`). A scene whose registered images use a
distorted camera model (:data:`DISTORTED_MODELS`: SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE — the
models gsplat's COLMAP parser accepts besides the two pinholes — and FULL_OPENCV, which nerfstudio's
OPENCV frames with a k3 map to) is turned into a PINHOLE scene here:

* :func:`undistorted_cameras` — the PINHOLE cameras the images are undistorted to (no I/O; what
  :func:`~cusgs_jax.data.loader.load_cameras` uses, so it still reads no image);
* :func:`undistorted_images` — the folder holding ``images/`` undistorted to exactly those
  cameras, made once and cached (what :func:`~cusgs_jax.data.loader.load_scene` reads).

**Why pycolmap** (``pycolmap.undistort_images``, COLMAP's own ``image_undistorter``) rather than
OpenCV's ``getOptimalNewCameraMatrix`` + ``remap`` as gsplat and nerfstudio do: it implements
exactly the camera models COLMAP wrote (same parameter order and conventions, including the
0.5-pixel centre and the fisheye models, where OpenCV needs a separate ``cv2.fisheye`` path and
gsplat its own equidistant remap), it is what the 3DGS / Scaffold-GS instructions tell users to
run (so a scene undistorted here equals one undistorted by hand), and pycolmap is already a
dependency — no OpenCV.

**Crop or mask** (``data.undistort``, :data:`MODES`):

* ``crop`` (default, what ``colmap image_undistorter``, gsplat and nerfstudio do): COLMAP's
  ``blank_pixels=0`` keeps the focal length and shrinks or grows the image to the largest centred
  rectangle in which every pixel comes from inside the distorted image, so no black (blank)
  border is left to be fitted as if it were scene content and no mask is needed. The undistorted
  image size therefore differs from the source size (larger for barrel, smaller for pincushion
  distortion), and the pixels outside that rectangle are lost.
* ``mask``: the undistorted camera is the source camera without its distortion — same size,
  focal lengths and principal point (``UndistortCameraOptions(blank_pixels=1, min_scale=1,
  max_scale=1)``) — so every source pixel that lands inside the frame is kept, and a *valid-pixel
  mask* per camera (``masks/camera_<id>.png``, 255 where the pixel's source location lies inside
  the distorted image: COLMAP's warp of an all-255 image, which leaves 0 outside) says which of
  the frame's pixels hold image content. :func:`undistorted_masks` reads it;
  :class:`~cusgs_jax.data.scene_data.SceneData` carries it as ``valid``, and the training loss, the
  held-out metrics and the feature targets ignore the pixels outside it
  (:func:`cusgs_jax.losses.image_loss`, :mod:`cusgs_jax.eval.views`).

**One common size.** The project trains on images of one size, but COLMAP gives each camera its
own undistorted size (per-image cameras, COLMAP's default, come out a few pixels apart). Every
undistorted camera is therefore centre-cropped to the smallest undistorted width and height
(principal point shifted by the crop offset; the cropped pixels are valid ones, so still no
border). Source cameras of different sizes are refused by the caller, as for pinhole scenes.

**data.downscale.** Pre-downscaled ``images_2/``, ``images_4/`` ... of a distorted scene hold
distorted pixels and are not used: the full-resolution ``images/`` are undistorted (once) and
:func:`~cusgs_jax.data.loader.load_scene` downscales the undistorted images on load with the
anti-aliased resize of :mod:`.images`, intrinsics divided by ``d`` as usual. Nothing is refused.

**Cache.** ``$CUSGS_CACHE_DIR/undistorted/<scene name>-<key>/`` (``~/.cache/cusgs_jax`` when the
variable is unset, as for the demo scene), holding ``images/`` and ``undistort.json`` (the cameras,
written last: a folder without it is never used). Nothing is ever written into the user's scene
folder, which may be read-only. ``<key>`` hashes everything the pixels depend on: each used
camera's model, size and exact parameters (what ``cameras.bin/.txt`` says about it), the
registered images' names and camera ids (what ``images.bin/.txt`` says about them), each image
file's size and modification time, the undistortion options, pycolmap's version and
:data:`CACHE_VERSION`; a changed image or re-calibrated camera gets a new folder (poses and points
are not part of it: they are read from the user's model every time). A folder is built in a
temporary sibling and renamed into place, so an interrupted run leaves nothing half-written and
two jobs racing on one scene both end up using one complete copy. Old folders are not removed
automatically; the ``undistorted/`` folder can be deleted at any time.

**Alpha.** COLMAP reads images as 8-bit RGB and drops an alpha channel, so an image with one
(RGBA, grey+alpha, palette with transparency) is undistorted here instead, with COLMAP's own warp
(``pycolmap.undistort_image``, the same bilinear resampling to the same camera): the colour
premultiplied by alpha and the alpha separately, then un-premultiplied and written as an RGBA PNG.
Loading composites it onto the background as for an undistorted scene (:mod:`.images`), and since
the warp is linear, ``rgb·a + bg·(1−a)`` of the undistorted pixels is the undistortion of the
image composited first (up to 8-bit rounding).

Limitations: JPEG images are re-encoded by COLMAP and, when cropped to the common size, once more
at quality 100; images with alpha are read as 8-bit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import pathlib
import re
import shutil
import tempfile
import time
import warnings
from typing import Any

import numpy as np

from cusgs_jax.cache import default_cache_dir  # $CUSGS_CACHE_DIR or ~/.cache/cusgs_jax
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.images import downscale_mask, scaled_size

__all__ = ["CACHE_VERSION", "DISTORTED_MODELS", "MODES", "PINHOLE_MODELS", "camera_model_name",
           "needs_undistortion", "undistort_options", "undistorted_cameras", "undistorted_images",
           "undistorted_masks"]

log = logging.getLogger("cusgs_jax")

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV")
CACHE_VERSION = 2  # 2: images with alpha keep it (RGBA)
MODES = ("crop", "mask")  # data.undistort (module docstring)
_MARKER = "undistort.json"
_STALE_TMP_SECONDS = 3600


def camera_model_name(camera) -> str:
    """The COLMAP model name of a pycolmap Camera (e.g. ``"OPENCV"``)."""
    return getattr(camera, "model_name", None) or getattr(camera.model, "name", str(camera.model))


def needs_undistortion(camera) -> bool:
    """True for a camera of :data:`DISTORTED_MODELS` with real distortion: a fisheye, or a
    perspective model with a non-zero distortion parameter (a SIMPLE_RADIAL with k = 0 is a
    pinhole and is loaded as one)."""
    model = camera_model_name(camera)
    if model not in DISTORTED_MODELS:
        return False
    if model == "OPENCV_FISHEYE":
        return True
    params = np.asarray(camera.params, np.float64)
    return bool(np.any(params[list(camera.extra_params_idxs())] != 0.0))


def undistort_options(mode: str):
    """COLMAP's ``UndistortCameraOptions`` for ``data.undistort=mode`` (module docstring): its
    defaults (``blank_pixels=0``, crop to the valid rectangle) for ``crop``; the source frame
    kept (``blank_pixels=1``, scale fixed at 1) for ``mask``."""
    import pycolmap

    if mode not in MODES:
        raise ValueError(f"undistortion mode {mode!r}: must be one of {', '.join(MODES)}")
    if mode == "mask":
        return pycolmap.UndistortCameraOptions(blank_pixels=1.0, min_scale=1.0, max_scale=1.0)
    return pycolmap.UndistortCameraOptions()


def _options(options, mode: str):
    return options if options is not None else undistort_options(mode)


@dataclasses.dataclass(frozen=True)
class _Plan:
    """How one source camera is undistorted: COLMAP's undistorted camera (``full``, its own
    size) and the centre crop ``(x0, y0)`` to the common size that gives ``camera``."""

    source_model: str  # the source camera's COLMAP model, e.g. "OPENCV"
    source: Any  # the source pycolmap.Camera
    full: Any  # pycolmap.Camera, PINHOLE
    x0: int
    y0: int
    camera: Any  # pycolmap.Camera, PINHOLE at the common size


def _plan(cameras: dict[int, Any], options) -> dict[int, _Plan]:
    """{camera id: _Plan} for the source ``cameras`` {id: pycolmap.Camera} (all of one size) and
    the (resolved) ``options``."""
    import pycolmap

    full = {cid: pycolmap.undistort_camera(options, cam) for cid, cam in cameras.items()}
    width = min(int(c.width) for c in full.values())
    height = min(int(c.height) for c in full.values())
    plans = {}
    for cid, cam in full.items():
        x0, y0 = (int(cam.width) - width) // 2, (int(cam.height) - height) // 2
        fx, fy = cam.focal_length_x, cam.focal_length_y
        cx, cy = cam.principal_point_x - x0, cam.principal_point_y - y0
        out = pycolmap.Camera(camera_id=cid, model="PINHOLE", width=width, height=height,
                              params=[fx, fy, cx, cy])
        plans[cid] = _Plan(source_model=camera_model_name(cameras[cid]), source=cameras[cid], full=cam, x0=x0, y0=y0,
                           camera=out)
    return plans


def undistorted_cameras(cameras: dict[int, Any], options=None, *, mode: str) -> dict[int, Any]:
    """The PINHOLE cameras that :func:`undistorted_images` undistorts to, without any I/O.

    Args:
      cameras: {camera id: pycolmap.Camera} of the registered images, all of one size; any of
        :data:`PINHOLE_MODELS` + :data:`DISTORTED_MODELS`.
      options: ``pycolmap.UndistortCameraOptions``; default :func:`undistort_options` ``(mode)``.
      mode: ``data.undistort``, "crop" or "mask" (module docstring).
    Returns:
      {camera id: pycolmap.Camera} PINHOLE, all of one common size (COLMAP's undistorted cameras,
      centre-cropped to the smallest undistorted width and height; for "mask" the source size).
    """
    return {cid: p.camera for cid, p in _plan(cameras, _options(options, mode)).items()}


# --------------------------------------------------------------------------------------------
# The cached undistorted images
# --------------------------------------------------------------------------------------------


def undistorted_images(scene: pathlib.Path, model_dir: pathlib.Path, views: list[tuple[str, int]],
                       cameras: dict[int, Any], *, cache_dir=None, options=None,
                       mode: str) -> pathlib.Path:
    """The cached folder whose ``images/`` hold the images of ``views`` undistorted to
    :func:`undistorted_cameras` ``(cameras)``, undistorting them first when not cached yet.

    Args:
      scene: the scene folder (``data.path``); its ``images/`` hold the full-resolution images.
        Only read.
      model_dir: the COLMAP model folder of the scene (``sparse/0``), given to COLMAP.
      views: [(image name, camera id), ...] of the registered images to undistort.
      cameras: {camera id: pycolmap.Camera} source cameras of ``views``, all of one size.
      cache_dir: root of the cache (default ``$CUSGS_CACHE_DIR`` or ``~/.cache/cusgs_jax``); the
        folder is ``<cache_dir>/undistorted/<scene name>-<key>`` (see the module docstring).
      options: ``pycolmap.UndistortCameraOptions``; default :func:`undistort_options` ``(mode)``.
      mode: ``data.undistort``, "crop" or "mask" (module docstring).
    Returns:
      The folder; ``<folder>/images/<name>`` is [H, W, 3] uint8 RGB at the common size (W, H)
      of the undistorted cameras, or [H, W, 4] RGBA (a PNG under the source's name) when the
      source image has an alpha channel (module docstring). For "mask", ``<folder>/masks/``
      holds each camera's valid-pixel mask (:func:`undistorted_masks`).
    Raises:
      SceneError: ``images/`` or an image is missing or unreadable, or the cache cannot be
        written.
    """
    import pycolmap

    options = _options(options, mode)
    sources = _source_files(scene, views)
    key = _cache_key(views, sources, cameras, options, pycolmap.__version__)
    root = pathlib.Path(cache_dir) if cache_dir is not None else default_cache_dir()
    final = root / "undistorted" / f"{_safe_name(scene)}-{key}"
    if (final / _MARKER).is_file():
        info = json.loads((final / _MARKER).read_text())
        log.info("using cached undistorted images of %s (%d images %s → PINHOLE %d×%d) in %s",
                 scene, len(views), info["source_models"], info["width"], info["height"], final)
        return final
    plans = _plan(cameras, options)
    _build(final, model_dir, scene, views, sources, plans, options, masks=mode == "mask")
    info = json.loads((final / _MARKER).read_text())
    crop = max((max(p.full.width - p.camera.width, p.full.height - p.camera.height)
                for p in plans.values()), default=0)
    valid = f" ({100 * info['valid_share']:.1f} % of the pixels valid, masked)" if info.get("masks") else ""
    log.info("undistorted %d images %s → PINHOLE %d×%d%s%s, cached in %s", len(views),
             info["source_models"], info["width"], info["height"],
             f" (cropped by up to {crop} px to one common size)" if crop else "", valid, final)
    return final


def _source_files(scene: pathlib.Path, views: list[tuple[str, int]]) -> list[pathlib.Path]:
    """The image file of every view in ``scene/images``; SceneError when one is missing."""
    folder = scene / "images"
    if not folder.is_dir():
        raise SceneError(
            f"no images folder: {folder} does not exist. The COLMAP cameras of {scene} are "
            "distorted, and undistorting them needs the full-resolution images the model was "
            "made from in images/ (pre-downscaled images_2/, images_4/ ... are distorted too and "
            "cannot be used as they are); put them there or set data.path to the right folder")
    paths = []
    for name, _ in views:
        path = folder / name
        if not path.is_file():
            raise SceneError(
                f"image {name!r} from the COLMAP model is missing: {path} does not exist; copy "
                f"it into {folder} or remove the image from the reconstruction (data.path={scene})")
        paths.append(path)
    return paths


def _cache_key(views, sources, cameras, options, colmap_version: str) -> str:
    """20 hex digits of sha256 over everything the undistorted pixels depend on (module docstring)."""
    cams = {str(cid): [camera_model_name(cam), int(cam.width), int(cam.height),
                       [float(p).hex() for p in np.asarray(cam.params, np.float64)]]
            for cid, cam in sorted(cameras.items())}
    images = []
    for (name, cid), path in zip(views, sources):
        st = path.stat()
        images.append([name, int(cid), st.st_size, st.st_mtime_ns])
    data = dict(version=CACHE_VERSION, pycolmap=colmap_version, options=options.todict(),
                cameras=cams, images=images)
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _safe_name(scene: pathlib.Path) -> str:
    """The scene folder's name reduced to [A-Za-z0-9._-] (at most 40 characters; "scene" if empty)."""
    name = scene.resolve().name
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")[:40] or "scene"


def _build(final: pathlib.Path, model_dir, scene, views, sources, plans, options, *, masks: bool) -> None:
    """Undistort into a temporary sibling of ``final`` and rename it into place (module docstring)."""
    root = final.parent
    try:
        root.mkdir(parents=True, exist_ok=True)
        _clear_stale(root, f".{final.name}.tmp-")
        if final.exists() and not (final / _MARKER).is_file():
            shutil.rmtree(final, ignore_errors=True)  # incomplete, not ours (e.g. a partial copy)
        tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=root))
    except OSError as e:
        raise SceneError(
            f"cannot write the undistorted images of {scene} to the cache folder {root}: "
            f"{type(e).__name__}: {e}; set CUSGS_CACHE_DIR to a writable folder with room for a "
            "copy of the images") from e
    try:
        _undistort_into(tmp, model_dir, scene, views, sources, plans, options, masks=masks)
        try:
            os.replace(tmp, final)
        except OSError:
            if not (final / _MARKER).is_file():  # lost a race only if the winner finished
                raise
    except OSError as e:
        raise SceneError(
            f"cannot write the undistorted images of {scene} to the cache folder {root}: "
            f"{type(e).__name__}: {e}; set CUSGS_CACHE_DIR to a writable folder with room for a "
            "copy of the images") from e
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _clear_stale(root: pathlib.Path, prefix: str) -> None:
    """Remove temporary folders of interrupted runs (older than an hour, so not in progress)."""
    for stale in root.glob(prefix + "*"):
        try:
            if time.time() - stale.stat().st_mtime > _STALE_TMP_SECONDS:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:
            pass


def _undistort_into(tmp: pathlib.Path, model_dir, scene, views, sources, plans, options, *, masks: bool) -> None:
    """Run COLMAP's undistorter into ``tmp``, check its output, crop to the common size, write the
    valid-pixel masks when asked, and the marker; only ``tmp/images``, ``tmp/masks`` and
    ``tmp/undistort.json`` are kept."""
    import pycolmap

    names = [name for name, _ in views]
    level = getattr(pycolmap.logging, "minloglevel", None)
    try:
        if level is not None:
            pycolmap.logging.minloglevel = max(int(level), 1)  # COLMAP's progress lines off
        pycolmap.undistort_images(str(tmp), str(model_dir), str(scene / "images"), names,
                                  undistort_options=options)
    except Exception as e:  # pycolmap raises RuntimeError, ValueError, ...
        raise SceneError(
            f"COLMAP's undistorter failed on {scene}: {type(e).__name__}: {e}. Undistort the "
            "scene yourself (`colmap image_undistorter --image_path <scene>/images --input_path "
            f"{model_dir} --output_path <undistorted scene> --output_type COLMAP`) and point "
            "data.path at the undistorted scene") from e
    finally:
        if level is not None:
            pycolmap.logging.minloglevel = level
    for entry in tmp.iterdir():  # sparse/ (stale poses/points if kept), stereo/, scripts
        if entry.name != "images":
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    alpha_images = []
    for (name, cid), source in zip(views, sources):
        _check_and_crop(tmp / "images" / name, source, plans[cid])
        if _has_alpha(source):
            _undistort_with_alpha(tmp / "images" / name, source, plans[cid], options)
            alpha_images.append(name)
    mask_files, shares = {}, []
    if masks:
        (tmp / "masks").mkdir()
        for cid, plan in plans.items():
            mask_files[str(cid)] = f"masks/camera_{cid}.png"
            shares.append(_write_mask(tmp / mask_files[str(cid)], plan, options))
    first = next(iter(plans.values())).camera
    info = dict(
        version=CACHE_VERSION, scene=str(scene.resolve()), num_images=len(views),
        source_models="+".join(sorted({p.source_model for p in plans.values()})),
        width=int(first.width), height=int(first.height),
        cameras={str(cid): dict(model="PINHOLE", width=int(p.camera.width),
                                height=int(p.camera.height),
                                params=[float(v) for v in p.camera.params], crop=[p.x0, p.y0])
                 for cid, p in plans.items()},
        alpha_images=alpha_images,
        masks=mask_files,
        **({"valid_share": float(np.mean(shares))} if shares else {}),  # mean over the cameras
    )
    (tmp / _MARKER).write_text(json.dumps(info, indent=1) + "\n")


def _check_and_crop(path: pathlib.Path, source: pathlib.Path, plan: _Plan) -> None:
    """Check the undistorted image at ``path`` has COLMAP's undistorted size and centre-crop it
    in place to the common size; SceneError when COLMAP could not read ``source``."""
    from PIL import Image

    if not path.is_file():
        raise SceneError(
            f"COLMAP's undistorter could not read image {source} (corrupt, or a format COLMAP "
            "cannot read): replace it with a valid PNG or JPEG, or remove it from the "
            "reconstruction")
    with Image.open(path) as im:
        size = im.size
    expected = (int(plan.full.width), int(plan.full.height))
    if size != expected:  # the undistorter and undistort_camera disagree (lenses.check_undistortable refuses the known cause)
        raise SceneError(f"COLMAP's undistorter made {source} {size[0]}x{size[1]} but its undistorted camera is "
                         f"{expected[0]}x{expected[1]}: its {plan.source_model} lens cannot be undistorted to one "
                         "pinhole image reliably; use data.undistort=lens")
    if (plan.full.width, plan.full.height) == (plan.camera.width, plan.camera.height):
        return
    import imageio.v3 as iio

    img = iio.imread(path)
    img = img[plan.y0:plan.y0 + int(plan.camera.height), plan.x0:plan.x0 + int(plan.camera.width)]
    kwargs = dict(quality=100, subsampling=0) if path.suffix.lower() in (".jpg", ".jpeg") else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        iio.imwrite(path, np.ascontiguousarray(img), **kwargs)


def _has_alpha(path: pathlib.Path) -> bool:
    """Whether the image file has an alpha channel (from its header)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    except Exception:  # unreadable files are reported by the size check
        return False


def _undistort_with_alpha(path: pathlib.Path, source: pathlib.Path, plan: _Plan, options) -> None:
    """Replace COLMAP's undistorted RGB image at ``path`` (alpha dropped) by the RGBA undistortion
    of ``source``: premultiplied colour [H, W, 3] and alpha [H, W] warped with
    ``pycolmap.undistort_image`` to ``plan.full``, centre-cropped like the others, colour
    un-premultiplied (0 where alpha is 0); written as a PNG whatever the name's extension."""
    from PIL import Image

    with Image.open(source) as im:
        rgba = np.asarray(im.convert("RGBA"))
    alpha = rgba[..., 3]
    premultiplied = np.round(rgba[..., :3] * (alpha[..., None] / 255.0)).astype(np.uint8)

    colour, a = _warp(options, premultiplied, plan).astype(np.float64), _warp(options, alpha, plan)
    straight = np.where(a[..., None] > 0, colour * 255.0 / np.maximum(a[..., None], 1), 0.0)
    out = np.concatenate([np.clip(np.round(straight), 0, 255).astype(np.uint8), a[..., None]], axis=-1)
    Image.fromarray(np.ascontiguousarray(out)).save(path, format="PNG")  # [H, W, 4] uint8: RGBA


# --------------------------------------------------------------------------------------------
# Valid-pixel masks (data.undistort=mask)
# --------------------------------------------------------------------------------------------


def _warp(options, img: np.ndarray, plan: _Plan) -> np.ndarray:
    """``img`` [h, w(, C)] uint8 at the source camera, warped with ``pycolmap.undistort_image`` to
    ``plan.full`` and centre-cropped to ``plan.camera``."""
    import pycolmap

    out, _ = pycolmap.undistort_image(options, pycolmap.Bitmap.from_array(np.ascontiguousarray(img)), plan.source)
    out = np.asarray(out.to_array())
    if out.shape[:2] != (int(plan.full.height), int(plan.full.width)):  # a bug, not the user's
        raise RuntimeError(f"COLMAP undistorted a {img.shape[1]}x{img.shape[0]} image to {out.shape[1]}x"
                           f"{out.shape[0]}, expected {int(plan.full.width)}x{int(plan.full.height)}")
    return out[plan.y0:plan.y0 + int(plan.camera.height), plan.x0:plan.x0 + int(plan.camera.width)]


def _write_mask(path: pathlib.Path, plan: _Plan, options) -> float:
    """Write the camera's valid-pixel mask [H, W] uint8 (255 valid, 0 not) as a PNG: COLMAP's warp of an
    all-255 source image, 255 exactly where the whole bilinear footprint lies inside the source.
    Returns the share of valid pixels."""
    from PIL import Image

    full = np.full((int(plan.source.height), int(plan.source.width)), 255, np.uint8)
    valid = _warp(options, full, plan) == 255
    Image.fromarray(np.where(valid, 255, 0).astype(np.uint8)).save(path, format="PNG")
    return float(valid.mean())


def _read_mask(path: pathlib.Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def undistorted_masks(folder: pathlib.Path, camera_ids: list[int], downscale: int) -> np.ndarray | None:
    """The valid-pixel masks of an undistorted folder, one per view, at the loaded size.

    Args:
      folder: a folder returned by :func:`undistorted_images`.
      camera_ids: [V] the views' camera ids (as given to :func:`undistorted_images`).
      downscale: ``data.downscale``; the masks are downscaled like the images
        (:func:`cusgs_jax.data.images.downscale_mask`).
    Returns:
      [V, H, W] bool, True where the pixel holds image content; None when the folder has no masks
      (``mode="crop"``: every pixel is valid).
    """
    info = json.loads((folder / _MARKER).read_text())
    files = info.get("masks") or {}
    if not files:
        return None
    per_camera = {}
    for cid, name in files.items():
        mask = _read_mask(folder / name) == 255
        if downscale > 1:
            out_hw = (scaled_size(mask.shape[0], downscale), scaled_size(mask.shape[1], downscale))
            mask = downscale_mask(mask, downscale, out_hw)
        per_camera[int(cid)] = mask
    return np.stack([per_camera[int(cid)] for cid in camera_ids])
