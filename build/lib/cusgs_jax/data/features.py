"""Dense per-view feature maps on disk: the format, a writer, a validating loader (and
:func:`resize_features`, re-exported from :mod:`.resize`).

On-disk format (one folder per feature model)::

    scene/features/<model>/meta.json          {"model", "dim", "resolution": [w, h], "source",
                                               "dtype", ...}
    scene/features/<model>/<image_stem>.npy   [h, w, D] float16 or float32, one per image

``<image_stem>`` is the image name from the COLMAP model without its extension (an image
``sub/img.jpg`` has its features in ``features/<model>/sub/img.npy``). A map may have any
resolution ``h × w`` (e.g. a ViT's patch grid) but must cover the *whole* image, not a crop; all
views of one model share one resolution. An all-zero vector means "no target at this pixel":
such pixels are left out of the feature losses (as in M3).

Shapes: N views, h × w feature-map resolution, D feature dimension.

Every problem with the files raises :class:`FeatureError` (a :class:`SceneError`), whose message
names the offending file and what to do about it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
from collections.abc import Mapping, Sequence
from typing import Any, Self

import numpy as np

from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.resize import resize_features

__all__ = [
    "FEATURES_DIR",
    "FeatureError",
    "FeatureSet",
    "FeatureWriter",
    "feature_dir",
    "feature_file",
    "list_feature_models",
    "load_features",
    "resize_features",
    "write_features",
]

FEATURES_DIR = "features"
META_FILE = "meta.json"
FORMAT_VERSION = 1
_MODEL_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")
_WRITE_DTYPES = ("float16", "float32")


class FeatureError(SceneError):
    """A problem with feature maps on disk (or their settings); the message says how to fix it."""


@dataclasses.dataclass(frozen=True, eq=False)  # arrays: compare/hash by identity
class FeatureSet:
    """The feature maps of one model for a list of views, in memory.

    Attributes:
      model: the model name (the folder name under ``features/``).
      maps: [N, h, w, D] float32 feature maps, in the order of the ``names`` they were loaded for
        (normally ``SceneData.names``, the scene's image order).
      valid: [N, h, w] bool, True where the vector has any non-zero component (a target).
      dim: D.
      resolution: (w, h) of the maps.
      meta: the parsed ``meta.json``.
      names: the image names, one per map.
    """

    model: str
    maps: np.ndarray
    valid: np.ndarray
    dim: int
    resolution: tuple[int, int]
    meta: dict
    names: tuple[str, ...] = ()

    @property
    def num_views(self) -> int:
        return int(self.maps.shape[0])


# --------------------------------------------------------------------------------------------
# Paths
# --------------------------------------------------------------------------------------------


def feature_dir(scene_path: str | os.PathLike, model: str) -> pathlib.Path:
    """``<scene>/features/<model>``."""
    return pathlib.Path(scene_path).expanduser() / FEATURES_DIR / model


def feature_file(scene_path: str | os.PathLike, model: str, name: str) -> pathlib.Path:
    """``<scene>/features/<model>/<name without extension>.npy`` for image ``name``."""
    rel = pathlib.PurePosixPath(str(name).replace("\\", "/"))
    if rel.is_absolute() or ".." in rel.parts or not rel.name:
        raise FeatureError(f"image name {name!r} cannot be mapped to a feature file: it must be a "
                           "relative path inside images/ (as stored in the COLMAP model)")
    return feature_dir(scene_path, model) / rel.with_suffix(".npy")


def _check_model_name(model: str) -> str:
    if not isinstance(model, str) or not _MODEL_NAME.match(model):
        raise FeatureError(f"feature model name {model!r} is not a valid folder name: use letters, "
                           "digits and _ . + - (e.g. 'daisy', 'clip', 'dinov2')")
    return model


def list_feature_models(scene_path: str | os.PathLike) -> list[str]:
    """Names of the feature models stored in ``<scene>/features/`` (folders holding a meta.json),
    sorted. Empty when there are none."""
    root = pathlib.Path(scene_path).expanduser() / FEATURES_DIR
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and (p / META_FILE).is_file())


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


class FeatureWriter:
    """Streams one model's feature maps to disk, one view at a time (what ``write_features`` and
    ``cusgs-extract`` use).

    Usage::

        with FeatureWriter(scene, "daisy", source="...", overwrite=True) as w:
            for name, fmap in ...:
                w.write(name, fmap)          # [h, w, D]
        # meta.json is written on a clean exit only

    On start it removes an existing ``meta.json`` of the model (and, with ``overwrite``, its old
    ``.npy`` files), so an interrupted run leaves a folder without ``meta.json``, which the loader
    reports as incomplete. Every file is written to a temporary name and renamed into place.
    """

    def __init__(self, scene_path: str | os.PathLike, model: str, *, source: str,
                 dtype: str = "float16", overwrite: bool = False,
                 extra_meta: Mapping[str, Any] | None = None):
        self.scene_path = pathlib.Path(scene_path).expanduser()
        self.model = _check_model_name(model)
        if str(dtype) not in _WRITE_DTYPES:
            raise FeatureError(f"feature dtype {dtype!r} is not supported: use one of "
                               f"{', '.join(_WRITE_DTYPES)}")
        self.dtype = np.dtype(str(dtype))
        self.source = str(source)
        self.extra_meta = dict(extra_meta or {})
        self.overwrite = bool(overwrite)
        self.dir = feature_dir(self.scene_path, model)
        self._shape: tuple[int, int, int] | None = None
        self._first: str | None = None
        self._files: dict[pathlib.Path, str] = {}
        self._any_valid = False
        self._started = False

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish()

    def start(self) -> None:
        if not self.scene_path.is_dir():
            raise FeatureError(f"scene folder {self.scene_path} does not exist: pass the folder "
                               "that contains images/ and sparse/0/")
        if self.dir.exists() and not self.dir.is_dir():
            raise FeatureError(f"{self.dir} is a file, not a folder: remove it")
        if self.dir.is_dir() and any(self.dir.iterdir()):
            if not self.overwrite:
                raise FeatureError(
                    f"features for model {self.model!r} already exist in {self.dir}: pass "
                    "overwrite=True (cusgs-extract --overwrite) to replace them, or delete the "
                    "folder")
            meta = self.dir / META_FILE
            if meta.exists():
                meta.unlink()
            for f in sorted(self.dir.rglob("*.npy")):
                f.unlink()
        self.dir.mkdir(parents=True, exist_ok=True)
        self._started = True

    def write(self, name: str, fmap: np.ndarray) -> pathlib.Path:
        """Write the [h, w, D] map of image ``name``; returns the file written."""
        if not self._started:
            self.start()
        path = feature_file(self.scene_path, self.model, name)
        if path in self._files:
            raise FeatureError(f"images {self._files[path]!r} and {name!r} map to the same feature "
                               f"file {path}: image names must differ by more than their extension")
        arr = np.asarray(fmap)
        if arr.ndim != 3 or min(arr.shape) < 1:
            raise FeatureError(f"feature map for {name!r} has shape {arr.shape}; expected "
                               "[h, w, D] with h, w, D >= 1")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise FeatureError(f"feature map for {name!r} has dtype {arr.dtype}; expected floats")
        if self._shape is None:
            self._shape, self._first = tuple(arr.shape), name
        elif tuple(arr.shape) != self._shape:
            raise FeatureError(f"feature map for {name!r} has shape {arr.shape} but the map for "
                               f"{self._first!r} has {self._shape}: all views of one model need "
                               "the same [h, w, D]")
        with np.errstate(over="ignore", invalid="ignore"):
            out = arr.astype(self.dtype)
        if not np.all(np.isfinite(out)):
            extra = (" (values beyond ±65504 overflow float16: scale the features or write "
                     "dtype='float32')" if self.dtype == np.float16 and np.all(np.isfinite(arr))
                     else "")
            raise FeatureError(f"feature map for {name!r} contains NaN or Inf values{extra}")
        self._any_valid = self._any_valid or bool(np.any(out != 0))
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_save(path, np.ascontiguousarray(out))
        self._files[path] = name
        return path

    def finish(self) -> pathlib.Path:
        """Write ``meta.json`` (after all maps); returns the feature folder."""
        if self._shape is None:
            raise FeatureError(f"no feature maps were written for model {self.model!r}")
        h, w, d = self._shape
        meta = {"model": self.model, "dim": int(d), "resolution": [int(w), int(h)],
                "source": self.source, "dtype": self.dtype.name, "num_views": len(self._files),
                "format_version": FORMAT_VERSION}
        meta.update(self.extra_meta)
        _atomic_write_text(self.dir / META_FILE, json.dumps(meta, indent=1) + "\n")
        return self.dir


def write_features(scene_path: str | os.PathLike, model: str,
                   maps: Mapping[str, np.ndarray] | np.ndarray,
                   names: Sequence[str] | None = None, *, source: str, dtype: str = "float16",
                   overwrite: bool = False,
                   extra_meta: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write one model's feature maps in the on-disk format.

    Args:
      scene_path: the scene folder (holding images/ and sparse/0/).
      model: model name, the folder under ``features/`` (letters, digits, ``_ . + -``).
      maps: either ``{image_name: [h, w, D] array}`` or an [N, h, w, D] array with ``names``.
        Zero vectors mean "no target". Any float (or integer) dtype; stored as ``dtype``.
      names: N image names (as in the COLMAP model) when ``maps`` is an array.
      source: free text describing where the features come from (stored in meta.json).
      dtype: "float16" (default, half the disk) or "float32".
      overwrite: replace an existing ``features/<model>`` (its meta.json and .npy files).
      extra_meta: more keys for meta.json.
    Returns:
      the folder ``<scene>/features/<model>``.
    Raises:
      FeatureError: bad shapes/dtypes, non-finite values (also after the cast to float16), name
        collisions, or existing features without ``overwrite``.
    """
    if isinstance(maps, Mapping):
        if names is not None:
            raise FeatureError("pass names only with an [N, h, w, D] array of maps, not a dict")
        items = list(maps.items())
    else:
        arr = np.asarray(maps)
        if arr.ndim != 4:
            raise FeatureError(f"maps has shape {arr.shape}; expected [N, h, w, D] (or a dict "
                               "of [h, w, D] maps keyed by image name)")
        if names is None or len(names) != arr.shape[0]:
            raise FeatureError(f"maps holds {arr.shape[0]} views: pass names with one image "
                               f"name per view (got {None if names is None else len(names)})")
        items = list(zip(names, arr))
    if not items:
        raise FeatureError(f"no feature maps given for model {model!r}")
    writer = FeatureWriter(scene_path, model, source=source, dtype=dtype, overwrite=overwrite,
                           extra_meta=extra_meta)
    with writer:
        for name, fmap in items:
            writer.write(name, fmap)
    return writer.dir


def _atomic_save(path: pathlib.Path, arr: np.ndarray) -> None:
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.npy")
    try:
        with open(tmp, "wb") as f:
            np.save(f, arr, allow_pickle=False)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _atomic_write_text(path: pathlib.Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def _read_meta(folder: pathlib.Path, model: str) -> dict:
    path = folder / META_FILE
    rerun = (f"rerun the extraction (e.g. `cusgs-extract <scene> --model {model} --overwrite`) or "
             "write the maps with cusgs_jax.data.features.write_features")
    if not path.is_file():
        npys = list(folder.glob("*.npy"))
        state = (f"the folder holds {len(npys)} .npy file(s) but no meta.json — the extraction "
                 "was interrupted or the files were copied without it" if npys else
                 "the folder is empty")
        raise FeatureError(f"feature metadata {path} is missing ({state}): {rerun}")
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FeatureError(f"cannot read feature metadata {path}: {type(e).__name__}: {e}; "
                           f"{rerun}") from e
    if not isinstance(meta, dict):
        raise FeatureError(f"feature metadata {path} is not a JSON object: {rerun}")
    dim = meta.get("dim")
    res = meta.get("resolution")
    if not isinstance(dim, int) or isinstance(dim, bool) or dim < 1:
        raise FeatureError(f"feature metadata {path} has dim={dim!r}; it must be a positive "
                           f"integer (the feature dimension D of the .npy files): fix it or {rerun}")
    if (not isinstance(res, (list, tuple)) or len(res) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res)):
        raise FeatureError(f"feature metadata {path} has resolution={res!r}; it must be [w, h] "
                           f"(positive integers, the maps' width and height): fix it or {rerun}")
    return meta


def _load_map(path: pathlib.Path, name: str, folder: pathlib.Path) -> np.ndarray:
    if not path.is_file():
        raise FeatureError(
            f"feature map for image {name!r} is missing: {path} does not exist; rerun the "
            f"extraction for all images of the scene (e.g. `cusgs-extract <scene> --model "
            f"{folder.name} --overwrite`) or add the file")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # corrupt file, pickled object array, ...
        raise FeatureError(f"cannot read feature map {path}: {type(e).__name__}: {e}; rewrite it "
                           "as a plain [h, w, D] float16/float32 .npy file") from e
    if not isinstance(arr, np.ndarray):
        raise FeatureError(f"feature map {path} is not a single array; save one [h, w, D] array "
                           "per image with np.save")
    if arr.ndim != 3:
        raise FeatureError(f"feature map {path} has shape {arr.shape} ({arr.ndim} dimensions); "
                           "expected [h, w, D] (height, width, feature dimension) — save one "
                           "map per image, without a batch axis")
    if not np.issubdtype(arr.dtype, np.floating):
        raise FeatureError(f"feature map {path} has dtype {arr.dtype}; expected float16 or "
                           "float32 — convert it with arr.astype(np.float32)")
    return arr


def _check_map_shape(arr: np.ndarray, path: pathlib.Path,
                     first: tuple[pathlib.Path, tuple[int, ...]] | None, meta_path: pathlib.Path,
                     meta: dict, image_size: tuple[int, int] | None) -> None:
    """FeatureError unless the [h, w, D] map ``arr`` (read from ``path``) has the shape of the
    first map (``first`` = (its path, its shape), None for the first) and of ``meta``
    (dim, resolution [w, h]), and — with ``image_size`` (W, H) — the image's aspect within 5 %."""
    dim, (mw, mh) = meta["dim"], meta["resolution"]
    if first is not None and arr.shape != first[1]:
        raise FeatureError(
            f"feature map {path} has shape {arr.shape} but {first[0]} has {first[1]} (and "
            f"{meta_path} says [h, w, D] = [{mh}, {mw}, {dim}]): all views of one model must "
            "share one resolution and dimension — re-extract or resize the odd ones")
    if arr.shape[2] != dim:
        raise FeatureError(
            f"feature map {path} has dimension D={arr.shape[2]} but {meta_path} says "
            f"dim={dim}: fix meta.json or re-extract the features")
    if (arr.shape[1], arr.shape[0]) != (mw, mh):
        raise FeatureError(
            f"feature map {path} is {arr.shape[1]}x{arr.shape[0]} (w x h) but {meta_path} "
            f"says resolution [{mw}, {mh}]: fix meta.json or re-extract the features")
    if image_size is not None:
        iw, ih = image_size
        if abs((mw / mh) / (iw / ih) - 1.0) > 0.05:
            raise FeatureError(
                f"feature map {path} is {mw}x{mh} (aspect {mw / mh:.3f}) but the image is "
                f"{iw}x{ih} (aspect {iw / ih:.3f}): a feature map must cover the whole image "
                "(not a crop or a padded square); re-extract it over the full image")


def load_features(scene_path: str | os.PathLike, model: str, names: Sequence[str], *,
                  image_size: tuple[int, int] | None = None) -> FeatureSet:
    """Load and validate one model's feature maps for the given views.

    Args:
      scene_path: the scene folder.
      model: the folder name under ``<scene>/features/``.
      names: the image names to load, in order (normally ``SceneData.names``).
      image_size: optional (W, H) of the images; when given, each map must have the same aspect
        ratio within 5 % (a map must cover the whole image, not a crop).
    Returns:
      FeatureSet with maps [N, h, w, D] float32 (N = len(names)) and valid [N, h, w] bool.
      Memory: N·h·w·D·4 bytes.
    Raises:
      FeatureError: missing folder (listing the models that exist), missing or bad meta.json,
        a missing per-image file, wrong ndim, non-float dtype, shapes disagreeing with meta.json
        or between views, NaN/Inf values, or no non-zero vector in any view.
    """
    scene = pathlib.Path(scene_path).expanduser()
    model = _check_model_name(model)
    folder = feature_dir(scene, model)
    if not folder.is_dir():
        available = list_feature_models(scene)
        have = (f"available models: {', '.join(available)}" if available else
                f"no feature models exist in {scene / FEATURES_DIR}")
        raise FeatureError(
            f"no features for model {model!r}: {folder} does not exist ({have}); extract them "
            f"with `cusgs-extract {scene} --model <daisy|hog|gabor|semantic|clip|dinov2>` or "
            "write them with cusgs_jax.data.features.write_features")
    meta = _read_meta(folder, model)
    meta_path = folder / META_FILE
    dim, (mw, mh) = meta["dim"], meta["resolution"]
    names = tuple(names)
    if not names:
        raise FeatureError(f"no image names given to load features {folder} for")

    maps = np.empty((len(names), mh, mw, dim), np.float32)
    first: tuple[pathlib.Path, tuple[int, ...]] | None = None
    for i, name in enumerate(names):
        path = feature_file(scene, model, name)
        arr = _load_map(path, name, folder)
        _check_map_shape(arr, path, first, meta_path, meta, image_size)
        if first is None:
            first = (path, arr.shape)
        out = maps[i]
        out[...] = arr  # casts to float32
        if not np.all(np.isfinite(out)):
            bad = int(np.sum(~np.isfinite(out)))
            raise FeatureError(f"feature map {path} contains {bad} NaN/Inf value(s): fix the "
                               "extractor or re-extract the features")
    valid = np.any(maps != 0, axis=-1)
    if not valid.any():
        raise FeatureError(
            f"all feature maps of model {model!r} in {folder} are all-zero: zero vectors mean "
            "'no target', so these features would train nothing — re-extract them (the "
            "extractor probably failed) or drop the model")
    return FeatureSet(model=model, maps=maps, valid=valid, dim=dim, resolution=(mw, mh),
                      meta=meta, names=names)
