"""Image files of a COLMAP scene: finding, reading, validating and downscaling them.

Used by :func:`cusgs_jax.data.loader.load_scene`. Images are read with imageio and returned as
[H, W, 3] uint8 RGB; ``downscale`` d means the loaded size is the camera size / d rounded half
up, taken from ``images_{d}/`` when that folder exists, else from ``images/`` downscaled with
anti-aliasing. Images with an alpha channel (RGBA, grey+alpha) are composited onto the
``background`` colour (the rendering background, ``splat.background``) as
``rgb·a + 255·bg·(1−a)``, and one warning per scene says so. Every problem raises
:class:`~cusgs_jax.data.errors.SceneError` naming the file.
"""

from __future__ import annotations

import logging
import math
import pathlib
from typing import Any

import numpy as np

from cusgs_jax.data.errors import SceneError

__all__ = ["check_background", "image_dir", "load_image", "load_images", "scaled_size"]

log = logging.getLogger("cusgs_jax")

_IMAGE_EXTENSIONS = (".png", ".PNG", ".jpg", ".JPG", ".jpeg", ".JPEG")


def scaled_size(size: int, downscale: int) -> int:
    """Expected loaded size: size / d rounded half up (Mip-NeRF 360's images_d sizes)."""
    return int(math.floor(size / downscale + 0.5))


def require_loadable_size(width: int, height: int, downscale: int, source) -> None:
    """SceneError unless ``width``×``height`` images of ``source`` keep at least a pixel a side at
    ``downscale`` (``data.downscale``); the message says how far it may go (11 pixels a side: the SSIM
    window that training and evaluation need)."""
    w, h = scaled_size(width, downscale), scaled_size(height, downscale)
    if w >= 1 and h >= 1:
        return
    fits = [d for d in range(1, downscale) if scaled_size(min(width, height), d) >= 11]
    fix = f"use data.downscale={max(fits)} or less" if fits else "use data.downscale=1"
    raise SceneError(f"data.downscale={downscale} shrinks the images ({width}x{height} in {source}) to {w}x{h} "
                     f"pixels; {fix}")


def image_dir(scene: pathlib.Path, downscale: int) -> tuple[pathlib.Path, bool]:
    """(folder to read, True when it already holds images downscaled by `downscale`)."""
    if downscale > 1:
        pre = scene / f"images_{downscale}"
        if pre.is_dir():
            return pre, True
    full = scene / "images"
    if not full.is_dir():
        extra = ""
        if downscale > 1:
            extra = f" (nor {scene / f'images_{downscale}'} for data.downscale={downscale})"
        raise SceneError(
            f"no images folder: {full} does not exist{extra}; put the images named in the COLMAP "
            "model there, or set data.path to the scene folder that contains images/ and "
            "sparse/0/")
    return full, False


def _find_image_file(folder: pathlib.Path, name: str, allow_other_ext: bool) -> pathlib.Path | None:
    """``folder / name``, or (``allow_other_ext``) the same stem with another image extension;
    None when there is none."""
    path = folder / name
    if path.is_file():
        return path
    if allow_other_ext:  # some datasets store images_d as .png next to .JPG originals
        stem = path.with_suffix("")
        for ext in _IMAGE_EXTENSIONS:
            cand = stem.with_suffix(ext)
            if cand.is_file():
                return cand
    return None


def check_background(background: Any) -> tuple[float, float, float]:
    """``background`` (``splat.background``) as an RGB tuple of 3 floats in [0, 1]; SceneError
    otherwise."""
    try:
        values = tuple(float(v) for v in background)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):  # also rejects NaN
        raise SceneError(f"splat.background={background!r} must be an RGB colour of three floats "
                         "in [0, 1], e.g. (0.0, 0.0, 0.0) for black or (1.0, 1.0, 1.0) for white")
    return values


def _split_channels(img: np.ndarray, path: pathlib.Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A decoded image ([H, W] or [H, W, 1|2|3|4]) → (colour [H, W, 3] with grey repeated,
    alpha [H, W] or None), both in the file's pixel type."""
    img = np.asarray(img)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4) or img.shape[0] == 0 or img.shape[1] == 0:
        raise SceneError(f"image {path} has an unsupported shape {img.shape} (expected a single "
                         "grey, RGB or RGBA picture); re-export it as a PNG or JPEG")
    channels = img.shape[-1]
    alpha = img[..., -1] if channels in (2, 4) else None
    if channels in (1, 2):  # grey or grey+alpha
        return np.repeat(img[..., :1], 3, axis=-1), alpha
    return img[..., :3], alpha


def _to_255(x: np.ndarray, path: pathlib.Path) -> np.ndarray:
    """Pixel values of any supported type (uint8/16, bool, int, float in [0, 1]) → float64 on
    the 8-bit scale [0, 255] (uint16 / 257, so 65535 → 255), same shape."""
    if x.dtype == np.uint8:
        return x.astype(np.float64)
    if x.dtype == np.bool_:
        return x.astype(np.float64) * 255.0
    if x.dtype == np.uint16:
        return x.astype(np.float64) / 257.0
    if np.issubdtype(x.dtype, np.floating):
        return np.clip(np.nan_to_num(x.astype(np.float64)), 0.0, 1.0) * 255.0
    if np.issubdtype(x.dtype, np.integer):
        return np.clip(x, 0, 255).astype(np.float64)
    raise SceneError(f"image {path} has an unsupported pixel type {x.dtype}; re-export it as "
                     "an 8-bit PNG or JPEG")


def to_rgb_uint8(img: np.ndarray, path: pathlib.Path,
                  background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """A decoded image ([H, W], [H, W, 1|2|3|4]; uint8/16, bool, int or float in [0, 1]) →
    ([H, W, 3] uint8 RGB, alpha [H, W] float64 in [0, 1] or None when it has none).

    Grey is repeated; an alpha channel ``a`` is composited onto ``background`` (RGB in [0, 1]):
    ``round(rgb·a + 255·bg·(1−a))`` in float64 on the 8-bit scale, so a fully opaque pixel
    keeps exactly its colour."""
    color, alpha = _split_channels(img, path)
    if alpha is None:
        if color.dtype == np.uint8:
            return np.ascontiguousarray(color), None
        return np.round(_to_255(color, path)).astype(np.uint8), None
    a = _to_255(alpha, path)[..., None] / 255.0  # [H, W, 1]
    bg = 255.0 * np.asarray(background, np.float64)
    out = _to_255(color, path) * a + bg * (1.0 - a)
    return np.clip(np.round(out), 0, 255).astype(np.uint8), a[..., 0]


def downscale_image(img: np.ndarray, factor: int, out_hw: tuple[int, int]) -> np.ndarray:
    """Anti-aliased downscale of a uint8 [H, W, 3] image to out_hw (≈ size / factor)."""
    h, w = img.shape[:2]
    oh, ow = out_hw
    if h == oh * factor and w == ow * factor:  # exact box filter
        out = img.reshape(oh, factor, ow, factor, 3).mean(axis=(1, 3), dtype=np.float32)
    else:
        from skimage.transform import resize
        out = resize(img.astype(np.float32), (oh, ow, 3), order=1, anti_aliasing=True,
                     preserve_range=True)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def downscale_mask(mask: np.ndarray, factor: int, out_hw: tuple[int, int]) -> np.ndarray:
    """A valid-pixel mask [H, W] bool downscaled like the images (:func:`downscale_image`) to ``out_hw``:
    a pixel stays valid only when the downscaled image there mixes in no invalid pixel."""
    rgb = np.repeat(np.where(mask, 255, 0).astype(np.uint8)[..., None], 3, axis=-1)
    return downscale_image(rgb, factor, out_hw)[..., 0] == 255


def _size_hint(img_w: int, cam: dict, from_prescaled: bool, downscale: int, folder: pathlib.Path,
               scene: pathlib.Path) -> str:
    """The second half of a wrong-image-size message: the likely cause and what to do."""
    ratio = cam["width"] / img_w
    k = round(ratio)
    if k >= 1 and abs(ratio - k) * img_w <= 1.0:
        if from_prescaled and k != downscale:
            return (f" The images in {folder.name}/ look {k}x smaller than the COLMAP cameras, not "
                    f"{downscale}x: rename the folder to images_{k}/ and set data.downscale={k}, "
                    f"or replace its contents with {downscale}x-downscaled images (or delete it "
                    "to have images/ downscaled on the fly).")
        if not from_prescaled and k > 1:
            return (f" The images in images/ look {k}x smaller than the COLMAP cameras (the "
                    "loader expects images/ at the model's full resolution): move them to "
                    f"{scene.name}/images_{k}/ and set data.downscale={k}, or put the "
                    "full-resolution images in images/.")
    return (" The images do not match this reconstruction (resized or cropped after SfM, or "
            "from another scene): use the images COLMAP was run on, or rerun SfM / "
            "undistortion on these.")


def load_image(folder: pathlib.Path, name: str, cam: dict, camera_id: int, downscale: int,
               from_prescaled: bool, scene: pathlib.Path, *,
               background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Read image ``name`` of camera ``cam`` (intrinsics dict with width, height) from
    ``folder``, check its size against the camera and downscale it when needed. An alpha
    channel is composited onto ``background`` (RGB in [0, 1], ``splat.background``).

    Returns:
      [h, w, 3] uint8 RGB, (h, w) = the camera size / ``downscale`` rounded half up.
    """
    return _load_image(folder, name, cam, camera_id, downscale, from_prescaled, scene,
                       check_background(background))[0]


def read_image_file(path: pathlib.Path, remove: str) -> np.ndarray:
    """The decoded pixels of the image file ``path``; SceneError naming the file when it is empty or
    cannot be decoded. ``remove``: how to drop the image instead of repairing it (the layout's way).

    imageio's own message for an undecodable file suggests installing more backends (``pip install
    imageio[pyav]``), which does not help a truncated or empty file: only its first sentence is kept.
    """
    fix = f"replace it with a valid copy or {remove}"
    try:
        size = path.stat().st_size
    except OSError as e:
        raise SceneError(f"cannot read image {path} ({e.strerror or e}): {fix}") from e
    if size == 0:
        raise SceneError(f"image {path} is an empty file (0 bytes), e.g. from an interrupted copy: {fix}")
    try:
        import imageio.v3 as iio

        return iio.imread(path)
    except Exception as e:  # imageio raises many types for a corrupt file
        detail = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        detail = detail.split(" Based on the extension")[0].rstrip(". ")
        raise SceneError(f"cannot decode image {path} ({size} bytes; {type(e).__name__}: {detail}): the file is "
                         f"corrupt or not an image; {fix}") from e


def _load_image(folder, name, cam, camera_id, downscale, from_prescaled, scene,
                background) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`load_image`, also returning the image's alpha ([H, W] float64 in [0, 1], at the
    file's size) or None when it has no alpha channel."""
    path = _find_image_file(folder, name, allow_other_ext=from_prescaled)
    if path is None:
        raise SceneError(
            f"image {name!r} from the COLMAP model is missing: {folder / name} does not exist; "
            f"copy it into {folder} or remove the image from the reconstruction (data.path="
            f"{scene})")
    raw = read_image_file(path, "remove the image from the reconstruction")
    img, alpha = to_rgb_uint8(raw, path, background)
    h, w = img.shape[:2]

    # Expected size of the file as read: the camera size, or the camera size / d for images_d.
    file_scale = downscale if from_prescaled else 1
    exp_w, exp_h = scaled_size(cam["width"], file_scale), scaled_size(cam["height"], file_scale)
    if abs(w - exp_w) > 1 or abs(h - exp_h) > 1:
        setting = (f"with data.downscale={downscale} " if from_prescaled else "")
        raise SceneError(
            f"image {path} is {w}x{h} but its camera {camera_id} ({cam['width']}x{cam['height']}) "
            f"means it should be {exp_w}x{exp_h} {setting}(±1 px)."
            + _size_hint(w, cam, from_prescaled, downscale, folder, scene))
    if not from_prescaled and downscale > 1:
        # Reduce the image to round(camera size / d) (anti-aliased).
        out_hw = (scaled_size(cam["height"], downscale), scaled_size(cam["width"], downscale))
        img = downscale_image(img, downscale, out_hw)
    return img, alpha


def load_images(folder: pathlib.Path, views: list[tuple[str, int]], cameras: dict[int, dict],
                downscale: int, from_prescaled: bool, scene: pathlib.Path, *,
                background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Read the images of ``views`` = [(name, camera id), ...] (cameras: id → intrinsics dict)
    with :func:`load_image` into one preallocated array. Images with an alpha channel are
    composited onto ``background`` (RGB in [0, 1], ``splat.background``), with one warning on
    the ``cusgs_jax`` logger saying how many.

    Returns:
      [V, H, W, 3] uint8 RGB, V = len(views).
    Raises:
      SceneError: a missing/unreadable/wrongly sized file, images loading at different sizes,
        or an invalid ``background``.
    """
    background = check_background(background)
    images = None
    with_alpha, transparent = [], 0
    for i, (name, camera_id) in enumerate(views):
        img, alpha = _load_image(folder, name, cameras[camera_id], camera_id, downscale,
                                 from_prescaled, scene, background)
        if alpha is not None:
            with_alpha.append(name)
            transparent += bool(np.any(alpha < 1.0))
        if images is None:
            images = np.empty((len(views),) + img.shape, np.uint8)
        elif img.shape != images.shape[1:]:
            h0, w0 = images.shape[1:3]
            h1, w1 = img.shape[:2]
            raise SceneError(
                f"images in {folder} differ in size: {views[0][0]!r} loads at {w0}x{h0} but "
                f"{name!r} at {w1}x{h1}; all training images must have one resolution — "
                "resize/crop them to a common size (and their cameras accordingly)")
        images[i] = img
    assert images is not None
    if with_alpha:
        warn_alpha(folder, with_alpha, transparent, len(views), background)
    return images


def warn_alpha(folder: pathlib.Path, with_alpha: list[str], transparent: int, total: int,
                background: tuple[float, float, float]) -> None:
    """The one warning per scene about images with an alpha channel (names: ``with_alpha``, of
    which ``transparent`` have a pixel with alpha < 1) composited onto ``background``."""
    example = ", ".join(repr(n) for n in with_alpha[:3]) + (", ..." if len(with_alpha) > 3 else "")
    bg = "(" + ", ".join(f"{v:g}" for v in background) + ")"
    log.warning(
        "%d of %d images in %s have an alpha channel (%s; %d with transparent pixels): they were "
        "composited onto the background colour %s, the rendering background — set "
        "splat.background to change it (e.g. (1.0, 1.0, 1.0) for images on white)",
        len(with_alpha), total, folder, example, transparent, bg)
