"""Feature extraction over a scene: dense per-view maps of one model, written in the on-disk
format of :mod:`cusgs_jax.data.features` (``<scene>/features/<model>/<image_stem>.npy`` +
``meta.json``).

Models (H×W the image size or ``resolution``):

========  =====================  =============================================================
model     D (default options)    what
========  =====================  =============================================================
daisy     104 (312 with lab)     :func:`~cusgs_jax.extract.descriptors.daisy_features`
hog       36 (108 with lab)      :func:`~cusgs_jax.extract.descriptors.hog_features`
gabor     18 (54 with lab)       :func:`~cusgs_jax.extract.descriptors.gabor_features`
semantic  32                     demo scene only: a fixed unit vector per object (orthogonal up to 32 ids)
                                 id from ``object_ids/<stem>.npy``; id 0 (nothing) → zero vector
vgg16     256                    ImageNet VGG16 relu3_3 at 1/4 resolution, unit vectors
                                 (:mod:`cusgs_jax.extract.vgg`; weights of the lpips extra)
clip      model width            optional: open_clip ViT patch tokens (local weights only)
dinov2    model width            optional: DINOv2 patch tokens via timm (local weights)
========  =====================  =============================================================

The first five (:data:`BUILT_IN_EXTRACTORS`) are deterministic and offline (the first four
weight-free; vgg16 needs the ``lpips`` extra's weight file and imports JAX, only when asked for)
and are extracted automatically when a run needs them; clip and dinov2 live in
:mod:`cusgs_jax.extract.pretrained` (torch is imported only when one is asked for).

Resolution: by default the maps have the loaded image size (the scene's ``data.downscale``); with
``resolution=(W, H)`` the image is first resized to W×H (anti-aliased; object ids by nearest
neighbour) and described there, so the descriptor's pixel-scale parameters refer to output
pixels. vgg16 maps are 1/4 of the image size, or ``resolution`` (the image is resized to 4×
it). The foundation models output their patch grid (long side = grid size), or are
area-resized to ``resolution``.

Extractor protocol (the registry ``_EXTRACTORS``): ``cls(model, options)`` validates the options
(``.opts``: the full option dict) and sets ``.source`` (meta "source"); ``extractor(view, size)``
maps a :class:`View` and the target size (w, h) or None to an [h, w, D] float map.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import pathlib
import sys
import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.data.demo.lens import LENS_MAPS, MASKED_MAPS  # the lens demo's maps in the masked / lens frame
from cusgs_jax.data.features import (
    META_FILE,
    FeatureError,
    FeatureWriter,
    feature_dir,
)
from cusgs_jax.extract.base import BUILT_IN_EXTRACTORS, MODELS, View, pop_options, resized_image
from cusgs_jax.extract.descriptors import (
    daisy_features,
    gabor_features,
    hog_features,
    semantic_features,
)
from cusgs_jax.extract.pretrained import PRETRAINED

__all__ = [
    "BUILT_IN_EXTRACTORS",
    "MODELS",
    "ExtractSummary",
    "ensure_extracted",
    "extract_scene",
]

# --------------------------------------------------------------------------------------------
# Extractors
# --------------------------------------------------------------------------------------------


class _Descriptor:
    """daisy / hog / gabor: a pure per-image function on the (resized) image."""

    _FNS: ClassVar[dict[str, tuple[Callable, dict]]] = {
        "daisy": (daisy_features, {"radius": 7, "rings": 2, "histograms": 6, "orientations": 8}),
        "hog": (hog_features, {"cell": 6, "orientations": 9}),
        "gabor": (gabor_features, {"frequencies": (0.08, 0.16, 0.32), "orientations": 6,
                                   "bandwidth": 1.0}),
    }

    def __init__(self, model: str, options: dict):
        self.fn, defaults = self._FNS[model]
        self.opts = pop_options(model, options, {**defaults, "lab": False})
        shown = ", ".join(f"{k}={v}" for k, v in self.opts.items())
        channels = "CIE-Lab channels (L/100, a/100, b/100)" if self.opts["lab"] else "grey image"
        self.source = (f"cusgs_jax.extract.{self.fn.__name__}({shown}) on the {channels}; "
                       "soft-L2-normalised")

    def __call__(self, view: View, size):
        """→ [h, w, D] float32 descriptors of the image resized to ``size`` = (w, h) (or not)."""
        return self.fn(resized_image(view.image, size), **self.opts)


class _Semantic:
    """semantic: per-object unit vectors from the demo scene's ``object_ids/<stem>.npy``."""

    def __init__(self, model: str, options: dict):
        self.opts = pop_options(model, options, {"dim": 32, "seed": 0})
        self.source = (f"cusgs_jax.extract.semantic_features(dim={self.opts['dim']}, "
                       f"seed={self.opts['seed']}) from the demo scene's object_ids/")

    def __call__(self, view: View, size):
        """→ [h, w, dim] float32; ids resized to ``size`` = (w, h) by nearest neighbour."""
        folder = view.maps_folder / "object_ids"
        if not folder.is_dir():
            raise FeatureError(
                f"model 'semantic' needs per-pixel object ids in {folder}, which does not exist: "
                "it is only available for the built-in demo scene (generate one with "
                "`cusgs-demo-scene OUT`); for other scenes use daisy, hog, gabor, vgg16, clip or dinov2")
        path = folder / pathlib.PurePosixPath(view.name).with_suffix(".npy")
        if not path.is_file():
            raise FeatureError(f"object ids for image {view.name!r} are missing: {path} does not "
                               "exist; regenerate the demo scene")
        try:
            ids = np.load(path, allow_pickle=False)
        except Exception as e:
            raise FeatureError(f"cannot read object ids {path}: {type(e).__name__}: {e}; "
                               "regenerate the demo scene") from e
        if ids.ndim != 2 or not np.issubdtype(ids.dtype, np.integer):
            raise FeatureError(f"object ids {path} must be an [H, W] integer array, got "
                               f"{ids.dtype} {ids.shape}; regenerate the demo scene")
        h, w = view.image.shape[:2]
        tw, th = size if size is not None else (w, h)
        if ids.shape != (th, tw):  # nearest neighbour: ids are labels
            rows = np.minimum(((np.arange(th) + 0.5) * ids.shape[0] / th).astype(int),
                              ids.shape[0] - 1)
            cols = np.minimum(((np.arange(tw) + 0.5) * ids.shape[1] / tw).astype(int),
                              ids.shape[1] - 1)
            ids = ids[rows][:, cols]
        return semantic_features(ids.astype(np.int64), dim=self.opts["dim"], seed=self.opts["seed"])


def _vgg16(model: str, options: dict):
    """The vgg16 extractor of :mod:`cusgs_jax.extract.vgg` (JAX is imported on first use)."""
    from cusgs_jax.extract.vgg import Vgg16  # lazy: vgg imports JAX; keeps cusgs-extract --help free of it

    return Vgg16(model, options)


def _pretrained(model: str, options: dict):
    """An extractor of :mod:`cusgs_jax.extract.pretrained` (torch is imported on first use)."""
    return PRETRAINED[model](model, options)


_EXTRACTORS: dict[str, Callable[[str, dict], Any]] = {
    "daisy": _Descriptor, "hog": _Descriptor, "gabor": _Descriptor, "semantic": _Semantic,
    "vgg16": _vgg16, "clip": _pretrained, "dinov2": _pretrained,
}


# --------------------------------------------------------------------------------------------
# Extraction over a scene
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ExtractSummary:
    """What :func:`extract_scene` wrote.

    Attributes:
      model: model name; folder: ``<scene>/features/<model>``; num_views: N maps written;
      dim: D; resolution: (w, h) of the maps; dtype: on-disk dtype; source: meta "source";
      seconds: total wall time; seconds_per_view: extraction time per view (excluding I/O);
      valid_fraction: fraction of pixels with a non-zero vector, over all views.
    """

    model: str
    folder: pathlib.Path
    num_views: int
    dim: int
    resolution: tuple[int, int]
    dtype: str
    source: str
    seconds: float
    seconds_per_view: float
    valid_fraction: float


def _check_request(scene: SceneData, model: str,
                   resolution: tuple[int, int] | None, overwrite: bool) -> tuple[int, int] | None:
    """Validate an :func:`extract_scene` request before any work; returns ``resolution`` as (W, H)
    ints (or None). Raises FeatureError on an unknown model, a bad resolution, or existing
    features without ``overwrite``; TypeError when ``scene`` is not a loaded scene."""
    if not isinstance(scene, SceneData):
        raise TypeError(f"scene must be a loaded cusgs_jax.data.scene_data.SceneData, got {type(scene).__name__}: "
                        "load it first (cusgs_jax.load_scene(path, DataConfig(...)))")
    if model not in _EXTRACTORS:
        raise FeatureError(f"unknown feature model {model!r}: choose one of {', '.join(MODELS)}")
    if resolution is not None:
        if (len(resolution) != 2 or
                not all(isinstance(v, (int, np.integer)) and v > 0 for v in resolution)):
            raise FeatureError(f"resolution={resolution!r} must be (W, H) positive integers")
        resolution = (int(resolution[0]), int(resolution[1]))
    folder = feature_dir(scene.path, model)
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:  # fail before the work
        raise FeatureError(f"features for model {model!r} already exist in {folder}: pass "
                           "--overwrite (overwrite=True) to replace them, or delete the folder")
    return resolution


def extract_scene(scene: SceneData, model: str, *, resolution: tuple[int, int] | None = None,
                  dtype: str = "float16", overwrite: bool = False, progress: bool = True,
                  **options) -> ExtractSummary:
    """Extract dense features of ``model`` for every image of a loaded scene and write them to
    ``<scene.path>/features/<model>/`` (see :mod:`cusgs_jax.data.features`).

    The maps describe the images as ``scene`` holds them: a run passes the scene it trains on (its
    ``data.downscale``, ``data.undistort`` and background), ``cusgs-extract`` loads one with its flags
    (:func:`cusgs_jax.data.loader.load_scene`) and passes it here.

    Args:
      scene: every view of it is described (the hold-out split does not matter).
      model: one of :data:`MODELS`.
      resolution: (W, H) of the maps; default: the loaded image size (descriptors), 1/4 of it
        (vgg16) or the patch grid (clip, dinov2).
      dtype: "float16" or "float32" on disk.
      overwrite: replace existing features of this model.
      progress: show a tqdm bar over the images.
      **options: per model — daisy: radius, rings, histograms, orientations, lab;
        hog: cell, orientations, lab; gabor: frequencies, orientations, bandwidth, lab;
        semantic: dim, seed; vgg16: layer; clip: weights, arch, device, net; dinov2: weights, arch,
        input_size, device, net.
    Returns:
      ExtractSummary (the maps themselves are on disk: ``load_features(scene, model, names)``). The meta of
      a masked or lens scene records ``"undistort": "mask"`` / ``"lens"`` (``SceneData.camera_frame``), so
      that a run with another mode refuses them (:func:`cusgs_jax.training.inputs.load_feature_targets`).
    Raises:
      FeatureError: unknown model/option, existing features without ``overwrite``, missing optional
      packages or weights.
    """
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    resolution = _check_request(scene, model, resolution, overwrite)
    extractor = _EXTRACTORS[model](model, dict(options))
    # the demo's object ids in the frame of these images: the lens demo keeps the masked frame's apart
    mode = scene.camera_frame
    maps = {"mask": scene.path / MASKED_MAPS, "lens": scene.path / LENS_MAPS}.get(mode)
    extra = {"extractor": "cusgs_jax.extract",
             **({"undistort": mode} if mode != "crop" else {}),
             "options": {k: v for k, v in getattr(extractor, "opts", {}).items()
                         if k not in ("weights", "device")},
             "image_size": [scene.width, scene.height]}
    writer = FeatureWriter(scene.path, model, source=extractor.source, dtype=dtype,
                           overwrite=overwrite, extra_meta=json.loads(json.dumps(extra)))
    busy, valid, total, shape = 0.0, 0, 0, None
    with writer:
        for i in tqdm(range(scene.num_images), desc=f"cusgs-extract {model}", unit="view",
                      disable=not progress, file=sys.stderr):
            view = View(scene.path, scene.names[i], scene.images[i], maps=maps)
            t0 = time.perf_counter()
            fmap = extractor(view, resolution)
            busy += time.perf_counter() - t0
            writer.write(view.name, fmap)
            nz = np.any(fmap != 0, axis=-1)
            valid, total, shape = valid + int(nz.sum()), total + nz.size, fmap.shape
    h, w, d = shape
    return ExtractSummary(model=model, folder=writer.dir, num_views=scene.num_images, dim=int(d),
                          resolution=(int(w), int(h)), dtype=writer.dtype.name,
                          source=extractor.source, seconds=time.perf_counter() - t_start,
                          seconds_per_view=busy / scene.num_images,
                          valid_fraction=valid / max(total, 1))


@contextlib.contextmanager
def _model_lock(scene_path: str | os.PathLike, model: str):
    """An exclusive inter-process lock (``flock``) on ``<scene>/features/.<model>.lock``."""
    lock_path = feature_dir(scene_path, model).with_name(f".{model}.lock")
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def ensure_extracted(scene: SceneData, model: str, **kwargs) -> bool:
    """Extract ``model``'s features unless a complete set (``meta.json``) is already there.

    Safe when several processes ask at once (the jobs of a parallel sweep on one
    scene): they serialise on a lock file beside the model folder, and the ones
    that wait find the finished set and return. A folder without ``meta.json``
    is an interrupted extraction and is replaced.

    Args:
      scene, model, **kwargs: as :func:`extract_scene` (``overwrite`` is decided here).
    Returns:
      True when this call extracted, False when the features were already there.
    """
    kwargs.pop("overwrite", None)
    if not isinstance(scene, SceneData):
        raise TypeError(f"scene must be a loaded SceneData, got {type(scene).__name__}")
    meta = feature_dir(scene.path, model) / META_FILE
    if meta.is_file():
        return False
    with _model_lock(scene.path, model):
        if meta.is_file():  # another process finished while we waited
            return False
        extract_scene(scene, model, overwrite=True, **kwargs)
    return True
