"""``cusgs-extract``: dense per-view feature maps for a scene, written in the on-disk format of
:mod:`cusgs_jax.data.features` (``<scene>/features/<model>/<image_stem>.npy`` + ``meta.json``).

Built-in extractors (deterministic, weight-free, offline; H×W the image size or ``resolution``):

========  =====================  =============================================================
model     D (default options)    what
========  =====================  =============================================================
daisy     104 (312 with lab)     ``skimage.feature.daisy`` at every pixel (step 1, radius 7,
                                 2 rings × 6 histograms × 8 orientations), image reflect-padded
                                 by the radius so the grid covers every pixel
hog       36 (108 with lab)      dense HOG: 9 unsigned orientations, soft-binned gradient
                                 magnitudes, 2×2 cells of 6×6 px centred on every pixel, L2-Hys
gabor     18 (54 with lab)       magnitudes of a ``skimage.filters.gabor`` bank (frequencies
                                 0.08, 0.16, 0.32 cycles/px × 6 orientations)
semantic  32                     demo scene only: a fixed unit vector per object (orthogonal up to 32 ids)
                                 id from ``object_ids/<stem>.npy``; id 0 (nothing) → zero vector
clip      model width            optional: open_clip ViT patch tokens (local weights only)
dinov2    model width            optional: DINOv2 patch tokens via transformers (local weights)
========  =====================  =============================================================

Normalisation (daisy, hog, gabor): every vector ``v`` becomes ``v / max(|v|, eps)`` — unit
length wherever the image has texture, shrinking smoothly towards zero on flat patches (weak,
noise-level texture is not blown up to unit length) and exactly zero (= "no target") where
``|v| < 1e-4·eps``, i.e. on perfectly flat ones. With ``lab`` the descriptor is computed on
each CIE-Lab channel (L/100, a/100, b/100), each block is normalised this way, the blocks are
concatenated (3·D) and the result divided by ``max(|v|, 1)``. ``eps`` per extractor (raw
descriptor units, grey image in [0, 1]): daisy 0.02, hog 0.01, gabor 0.005; on the demo scene
> 98 % of the pixels get unit vectors (daisy 100 %).

Resolution: by default the maps have the loaded image size (``downscale``); with
``resolution=(W, H)`` the image is first resized to W×H (anti-aliased; object ids by nearest
neighbour) and described there, so the descriptor's pixel-scale parameters refer to output
pixels. The foundation models output their patch grid (long side = grid size), or are
area-resized to ``resolution``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import fcntl
import json
import os
import pathlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np

from cusgs_jax.data.colmap import SceneError, load_scene
from cusgs_jax.data.features import (
    META_FILE,
    FeatureError,
    FeatureWriter,
    feature_dir,
    resize_features,
)

__all__ = [
    "BUILTIN_MODELS",
    "MODELS",
    "ExtractSummary",
    "daisy_features",
    "ensure_extracted",
    "extract",
    "gabor_features",
    "hog_features",
    "main",
    "semantic_features",
    "semantic_palette",
]

BUILTIN_MODELS = ("daisy", "hog", "gabor", "semantic")
MODELS = BUILTIN_MODELS + ("clip", "dinov2")

_DAISY_EPS, _HOG_EPS, _GABOR_EPS = 0.02, 0.01, 0.005
_SEMANTIC_SALT = 0x5E6A471C


# --------------------------------------------------------------------------------------------
# Per-image descriptors (pure functions)
# --------------------------------------------------------------------------------------------


def _channels(image: np.ndarray, lab: bool) -> list[np.ndarray]:
    """[H, W, 3] uint8/float RGB → list of [H, W] float64 channels: grey in [0, 1], or
    Lab / 100."""
    from skimage import color, util

    img = util.img_as_float(np.asarray(image))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] < 3:
        raise ValueError(f"image must be [H, W, 3] RGB, got shape {img.shape}")
    img = img[..., :3]
    if lab:
        lab_img = color.rgb2lab(img) / 100.0
        return [lab_img[..., c] for c in range(3)]
    return [color.rgb2gray(img)]


def _soft_normalise(v: np.ndarray, eps: float) -> np.ndarray:
    """[..., D] → v / max(|v|, eps) (float32); exactly zero where |v| < 1e-4·eps (round-off on
    a flat patch)."""
    norm = np.sqrt(np.sum(np.square(v, dtype=np.float64), axis=-1, keepdims=True))
    out = v / np.maximum(norm, eps)
    return np.where(norm < 1e-4 * eps, 0.0, out).astype(np.float32)


def _per_channel(image, lab: bool, fn: Callable[[np.ndarray], np.ndarray], eps: float):
    blocks = [_soft_normalise(fn(ch), eps) for ch in _channels(image, lab)]
    if len(blocks) == 1:
        return blocks[0]
    return _soft_normalise(np.concatenate(blocks, axis=-1), 1.0)


def daisy_features(image: np.ndarray, *, radius: int = 7, rings: int = 2, histograms: int = 6,
                   orientations: int = 8, lab: bool = False) -> np.ndarray:
    """Dense DAISY descriptor at every pixel.

    ``skimage.feature.daisy(step=1, normalization='off')`` on the channel reflect-padded by
    ``radius``, so descriptor (i, j) is centred on pixel (i, j); then soft L2 normalisation
    (module docstring). About 30 ms for a 160×120 grey view.

    Args:
      image: [H, W, 3] RGB (uint8, or float in [0, 1]).
      radius, rings, histograms, orientations: DAISY parameters.
      lab: describe the L, a, b channels separately and concatenate.
    Returns:
      [H, W, D] float32, D = orientations·(rings·histograms + 1) (104 by default), ×3 with lab.
    """
    from skimage.feature import daisy

    def one(ch):
        padded = np.pad(ch, radius, mode="reflect")
        return daisy(padded, step=1, radius=radius, rings=rings, histograms=histograms,
                     orientations=orientations, normalization="off")

    return _per_channel(image, lab, one, _DAISY_EPS)


def _hog_channel(ch: np.ndarray, cell: int, orientations: int) -> np.ndarray:
    """[H, W] → [H, W, 4·orientations] un-normalised dense HOG block (cell means)."""
    h, w = ch.shape
    p = np.pad(ch, 1, mode="edge")
    gy = p[2:, 1:-1] - p[:-2, 1:-1]  # central differences (as skimage.feature.hog)
    gx = p[1:-1, 2:] - p[1:-1, :-2]
    mag = np.hypot(gx, gy)
    # Unsigned orientation in [0, π), linearly split between the two nearest bin centres
    # (centres at (b + 0.5)·π/n, circular).
    pos = (np.arctan2(gy, gx) % np.pi) / (np.pi / orientations) - 0.5
    lo = np.floor(pos)
    frac = pos - lo
    b0 = lo.astype(np.int64) % orientations
    b1 = (b0 + 1) % orientations
    hist = np.zeros((h, w, orientations))
    for b in range(orientations):
        hist[..., b] = mag * ((b0 == b) * (1.0 - frac) + (b1 == b) * frac)
    # Cells: [i+0.5-c, i+0.5] and [i+0.5, i+0.5+c] in continuous pixel coordinates (pixel i spans
    # [i, i+1]), i.e. exactly centred on the pixel centre: average neighbouring samples (so the
    # end pixels count half) and box-sum c of them with a summed-area table.
    pad = cell + 1
    hp = np.pad(hist, ((pad, pad), (pad, pad), (0, 0)), mode="symmetric")
    hp = 0.5 * (hp[1:] + hp[:-1])
    hp = 0.5 * (hp[:, 1:] + hp[:, :-1])
    sat = np.zeros((hp.shape[0] + 1, hp.shape[1] + 1, orientations))
    sat[1:, 1:] = hp.cumsum(0).cumsum(1)

    def box(dr, dc):  # sum over rows [i+dr, i+dr+c), cols [j+dc, j+dc+c) of the smoothed map
        r0, c0 = pad + dr, pad + dc
        r1, c1 = r0 + cell, c0 + cell
        return (sat[r1:r1 + h, c1:c1 + w] - sat[r0:r0 + h, c1:c1 + w]
                - sat[r1:r1 + h, c0:c0 + w] + sat[r0:r0 + h, c0:c0 + w])

    cells = [box(dr, dc) for dr in (-cell, 0) for dc in (-cell, 0)]
    return np.concatenate(cells, axis=-1) / (cell * cell)


def hog_features(image: np.ndarray, *, cell: int = 6, orientations: int = 9,
                 lab: bool = False) -> np.ndarray:
    """Dense HOG: one Dalal–Triggs block centred on every pixel.

    Per pixel: gradients by central differences, magnitude split linearly between the two
    nearest of ``orientations`` unsigned (0–180°) bins; the block is 2×2 cells of
    ``cell``×``cell`` px meeting at the pixel centre, each cell the mean histogram over its area;
    the 4·orientations block is L2-Hys normalised (soft L2, clip at 0.2, soft L2 again; see the
    module docstring for the soft normalisation). Unlike ``skimage.feature.hog`` (blocks on a
    cell grid, hard binning) this gives a smooth per-pixel field.

    Args:
      image: [H, W, 3] RGB (uint8, or float in [0, 1]).
      cell: cell side in pixels.
      orientations: histogram bins.
      lab: per Lab channel, concatenated.
    Returns:
      [H, W, 4·orientations] float32 (36 by default), ×3 with lab.
    """

    def one(ch):  # L2-Hys with the soft normalisation; the result has norm <= 1
        v = _soft_normalise(_hog_channel(ch, cell, orientations), _HOG_EPS)
        norm = np.linalg.norm(v, axis=-1, keepdims=True)
        clipped = np.minimum(v, 0.2)
        return clipped * (norm / np.maximum(np.linalg.norm(clipped, axis=-1, keepdims=True),
                                            1e-12))

    return _per_channel(image, lab, one, 1.0)


def _gabor_bank(frequencies, orientations, bandwidth, zero_mean=True):
    """``skimage.filters.gabor_kernel`` for every (frequency, orientation); with ``zero_mean`` the
    real part's mean is subtracted (its DC response: small, ~0.1–0.2 % of the kernel's L1 mass,
    but without it a flat patch gives a brightness-dependent response), so a flat patch responds
    with (numerically) zero."""
    from skimage.filters import gabor_kernel

    bank = []
    for f in frequencies:
        for k in range(orientations):
            g = gabor_kernel(f, theta=np.pi * k / orientations, bandwidth=bandwidth)
            if zero_mean:
                g = g - g.real.mean()
            bank.append(g)
    return bank


def _gabor_channel(ch: np.ndarray, kernels) -> np.ndarray:
    """[H, W] → [H, W, len(kernels)] |ch ⊛ g| with reflect borders (same as
    ``skimage.filters.gabor(mode='reflect')``), by FFT."""
    from scipy import fft

    h, w = ch.shape
    rmax = max(max(k.shape) for k in kernels) // 2
    padded = np.pad(ch, rmax, mode="symmetric")  # numpy 'symmetric' == ndimage 'reflect'
    shape = (fft.next_fast_len(padded.shape[0] + 2 * rmax),
             fft.next_fast_len(padded.shape[1] + 2 * rmax))
    spec = fft.fft2(padded, shape)
    out = np.empty((h, w, len(kernels)))
    for n, k in enumerate(kernels):
        kr, kc = k.shape[0] // 2, k.shape[1] // 2
        full = fft.ifft2(spec * fft.fft2(k, shape))
        # full[y, x] = Σ padded[y-u, x-v]·k[u, v]; output pixel (i, j) ↔ y = i + rmax + kr.
        out[..., n] = np.abs(full[rmax + kr:rmax + kr + h, rmax + kc:rmax + kc + w])
    return out


def gabor_features(image: np.ndarray, *, frequencies: Sequence[float] = (0.08, 0.16, 0.32),
                   orientations: int = 6, bandwidth: float = 1.0,
                   lab: bool = False) -> np.ndarray:
    """Magnitudes of a Gabor filter bank at every pixel.

    For each frequency f (cycles/px) and orientation θ = kπ/orientations the magnitude
    ``hypot(*skimage.filters.gabor(ch, f, theta=θ, bandwidth=bandwidth, mode='reflect'))``
    (computed by FFT, identical up to rounding), except that the kernel's real part is made
    zero-mean (no response to flat patches, hence no brightness dependence); then soft L2
    normalisation.

    Args:
      image: [H, W, 3] RGB (uint8, or float in [0, 1]).
      frequencies, orientations, bandwidth: the bank.
    Returns:
      [H, W, len(frequencies)·orientations] float32 (18 by default), ×3 with lab.
    """
    kernels = _gabor_bank(tuple(frequencies), orientations, bandwidth)
    return _per_channel(image, lab, lambda ch: _gabor_channel(ch, kernels), _GABOR_EPS)


def semantic_palette(dim: int = 32, seed: int = 0, num_ids: int = 256) -> np.ndarray:
    """[num_ids, dim] float32 unit vectors per object id; row 0 is zero.

    Ids 1…dim get the rows of one fixed random orthogonal matrix (seeded by
    ``seed`` only), so up to ``dim`` objects are mutually orthogonal — an
    exactly consistent, perfectly separable semantic channel, which makes the
    ground-truth row of the retrieval protocol a true upper bound. Further ids
    get pseudo-random unit vectors seeded by (seed, id). No row depends on which
    other ids exist.
    """
    table = np.zeros((num_ids, dim), np.float32)
    basis, _ = np.linalg.qr(np.random.default_rng([_SEMANTIC_SALT, seed]).standard_normal((dim, dim)))
    for k in range(1, num_ids):
        if k <= dim:
            table[k] = basis[k - 1]
        else:
            v = np.random.default_rng([_SEMANTIC_SALT, seed, k]).standard_normal(dim)
            table[k] = v / np.linalg.norm(v)
    return table


def semantic_features(object_ids: np.ndarray, *, dim: int = 32, seed: int = 0) -> np.ndarray:
    """[H, W] integer object ids (0 = none) → [H, W, dim] float32 per-object unit vectors
    (:func:`semantic_palette`); id-0 pixels get the zero vector (no target)."""
    ids = np.asarray(object_ids)
    if ids.ndim != 2 or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"object ids must be an [H, W] integer array, got {ids.dtype} {ids.shape}")
    if ids.size and (ids.min() < 0 or ids.max() > 65535):
        raise ValueError("object ids must lie in [0, 65535]")
    num = int(ids.max()) + 1 if ids.size else 1
    return semantic_palette(dim, seed, max(num, 2))[ids]


# --------------------------------------------------------------------------------------------
# Extractors over a scene
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _View:
    scene: pathlib.Path
    name: str
    image: np.ndarray  # [H, W, 3] uint8 at the loaded resolution


def _resized_image(image: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """[H, W, 3] uint8 → [h, w, 3] float in [0, 1] (anti-aliased resize when size=(w, h))."""
    from skimage import transform, util

    img = util.img_as_float(image)
    if size is None or (img.shape[1], img.shape[0]) == tuple(size):
        return img
    w, h = size
    return np.clip(transform.resize(img, (h, w, 3), order=1, anti_aliasing=True), 0.0, 1.0)


def _pop_options(model: str, options: dict, allowed: dict) -> dict:
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise FeatureError(f"option(s) {', '.join(unknown)} not supported by model {model!r}; "
                           f"it accepts: {', '.join(sorted(allowed)) or 'none'}")
    return {**allowed, **options}


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
        self.opts = _pop_options(model, options, {**defaults, "lab": False})
        shown = ", ".join(f"{k}={v}" for k, v in self.opts.items())
        channels = "CIE-Lab channels (L/100, a/100, b/100)" if self.opts["lab"] else "grey image"
        self.source = (f"cusgs_jax.extract.{self.fn.__name__}({shown}) on the {channels}; "
                       "soft-L2-normalised")

    def __call__(self, view: _View, size):
        return self.fn(_resized_image(view.image, size), **self.opts)


class _Semantic:
    def __init__(self, model: str, options: dict):
        self.opts = _pop_options(model, options, {"dim": 32, "seed": 0})
        self.palette = None
        self.source = (f"cusgs_jax.extract.semantic_features(dim={self.opts['dim']}, "
                       f"seed={self.opts['seed']}) from the demo scene's object_ids/")

    def __call__(self, view: _View, size):
        folder = view.scene / "object_ids"
        if not folder.is_dir():
            raise FeatureError(
                f"model 'semantic' needs per-pixel object ids in {folder}, which does not exist: "
                "it is only available for the built-in demo scene (generate one with "
                "`cusgs-demo-scene OUT`); for other scenes use daisy, hog, gabor, clip or dinov2")
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


_INSTALL_HINT = {
    "clip": "pip install torch open_clip_torch",
    "dinov2": "pip install torch transformers",
}
_WEIGHTS_HINT = {
    "clip": ("an open_clip checkpoint file (e.g. open_clip_pytorch_model.bin of "
             "laion/CLIP-ViT-B-16-laion2B-s34B-b88K, with --arch ViT-B-16), copied to this "
             "machine"),
    "dinov2": ("a local Hugging Face snapshot folder of a DINOv2 model (config.json + "
               "model.safetensors, e.g. facebook/dinov2-small), copied to this machine"),
}


def _require_weights(model: str, weights) -> pathlib.Path:
    if not weights:
        raise FeatureError(
            f"model {model!r} needs local weights: pass --weights PATH (weights=PATH), {model} "
            f"weights being {_WEIGHTS_HINT[model]}. Nothing is ever downloaded. Install the "
            f"optional dependencies with `{_INSTALL_HINT[model]}`.")
    path = pathlib.Path(weights).expanduser()
    if not path.exists():
        raise FeatureError(f"weights for model {model!r} not found: {path} does not exist; pass "
                           f"--weights pointing at {_WEIGHTS_HINT[model]}")
    return path


def _require_modules(model: str, modules: Sequence[str]):
    import importlib

    loaded = []
    for mod in modules:
        try:
            loaded.append(importlib.import_module(mod))
        except ImportError as e:
            raise FeatureError(
                f"model {model!r} needs the optional package {mod!r}, which is not installed "
                f"({e}): install it with `{_INSTALL_HINT[model]}`, or use a built-in model "
                f"({', '.join(BUILTIN_MODELS)})") from e
    return loaded


def _grid_size(size, grid_hw) -> tuple[int, int]:
    return (int(size[0]), int(size[1])) if size is not None else (grid_hw[1], grid_hw[0])


class _Clip:
    """open_clip ViT patch tokens, projected into the joint embedding space (no MaskCLIP-style
    modification). The whole image is resized to the model's square input."""

    def __init__(self, model: str, options: dict):
        self.opts = _pop_options(model, options, {"weights": None, "arch": "ViT-B-16",
                                                  "device": "cpu"})
        weights = _require_weights("clip", self.opts["weights"])
        self.torch, open_clip = _require_modules("clip", ("torch", "open_clip"))
        net, _, _ = open_clip.create_model_and_transforms(self.opts["arch"],
                                                          pretrained=str(weights))
        self.visual = net.visual.eval().to(self.opts["device"])
        self.visual.output_tokens = True
        size = self.visual.image_size
        self.input = size if isinstance(size, int) else int(size[0])
        self.source = f"open_clip {self.opts['arch']} patch tokens, weights {weights}"

    def __call__(self, view: _View, size):
        torch = self.torch
        img = _resized_image(view.image, (self.input, self.input))
        mean = np.array([0.48145466, 0.4578275, 0.40821073])
        std = np.array([0.26862954, 0.26130258, 0.27577711])
        x = torch.from_numpy(((img - mean) / std).transpose(2, 0, 1)[None].astype(np.float32))
        with torch.no_grad():
            pooled, tokens = self.visual(x.to(self.opts["device"]))
            proj = getattr(self.visual, "proj", None)
            if proj is not None and tokens.shape[-1] != pooled.shape[-1]:
                tokens = tokens @ proj
        tokens = tokens[0].float().cpu().numpy()
        g = round(float(np.sqrt(tokens.shape[0])))
        grid = tokens.reshape(g, g, -1)
        h, w = view.image.shape[:2]
        default = (g, max(1, round(g * h / w))) if w >= h else (max(1, round(g * w / h)), g)
        return resize_features(grid, size if size is not None else default)


class _Dinov2:
    """DINOv2 patch tokens (last layer) from a local Hugging Face snapshot via transformers; the
    image keeps its aspect, its long side resized to ``input_size`` (a multiple of 14)."""

    def __init__(self, model: str, options: dict):
        self.opts = _pop_options(model, options, {"weights": None, "input_size": 448,
                                                  "device": "cpu"})
        weights = _require_weights("dinov2", self.opts["weights"])
        self.torch, transformers = _require_modules("dinov2", ("torch", "transformers"))
        self.net = transformers.AutoModel.from_pretrained(str(weights), local_files_only=True)
        self.net = self.net.eval().to(self.opts["device"])
        self.patch = int(getattr(self.net.config, "patch_size", 14))
        self.skip = 1 + int(getattr(self.net.config, "num_register_tokens", 0) or 0)
        self.source = f"DINOv2 last-layer patch tokens (transformers), weights {weights}"

    def __call__(self, view: _View, size):
        torch = self.torch
        h, w = view.image.shape[:2]
        s = self.opts["input_size"] / max(h, w)
        gh = max(1, round(h * s / self.patch))
        gw = max(1, round(w * s / self.patch))
        img = _resized_image(view.image, (gw * self.patch, gh * self.patch))
        mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
        x = torch.from_numpy(((img - mean) / std).transpose(2, 0, 1)[None].astype(np.float32))
        with torch.no_grad():
            out = self.net(pixel_values=x.to(self.opts["device"])).last_hidden_state
        grid = out[0, self.skip:].float().cpu().numpy().reshape(gh, gw, -1)
        return resize_features(grid, _grid_size(size, (gh, gw)))


_EXTRACTORS: dict[str, Callable[[str, dict], Any]] = {
    "daisy": _Descriptor, "hog": _Descriptor, "gabor": _Descriptor, "semantic": _Semantic,
    "clip": _Clip, "dinov2": _Dinov2,
}


@dataclasses.dataclass(frozen=True)
class ExtractSummary:
    """What :func:`extract` wrote.

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


def extract(scene_path: str | os.PathLike, model: str, *,
            resolution: tuple[int, int] | None = None, downscale: int = 1,
            dtype: str = "float16", overwrite: bool = False, progress: bool = True,
            **options) -> ExtractSummary:
    """Extract dense features of ``model`` for every image of a COLMAP scene and write them to
    ``<scene>/features/<model>/`` (see :mod:`cusgs_jax.data.features`).

    Args:
      scene_path: scene folder (images/ + sparse/0/), loaded with ``load_scene``.
      model: one of :data:`MODELS`.
      resolution: (W, H) of the maps; default: the loaded image size (built-ins) or the patch
        grid (clip, dinov2).
      downscale: ``load_scene`` downscale factor of the images described.
      dtype: "float16" or "float32" on disk.
      overwrite: replace existing features of this model.
      progress: show a tqdm bar over the images.
      **options: per model — daisy: radius, rings, histograms, orientations, lab;
        hog: cell, orientations, lab; gabor: frequencies, orientations, bandwidth, lab;
        semantic: dim, seed; clip: weights, arch, device; dinov2: weights, input_size, device.
    Returns:
      ExtractSummary (the maps themselves are on disk: ``load_features(scene, model, names)``).
    Raises:
      SceneError / FeatureError: bad scene, unknown model/option, existing features without
      ``overwrite``, missing optional packages or weights.
    """
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    if model not in _EXTRACTORS:
        raise FeatureError(f"unknown feature model {model!r}: choose one of {', '.join(MODELS)}")
    if resolution is not None:
        if (len(resolution) != 2 or
                not all(isinstance(v, (int, np.integer)) and v > 0 for v in resolution)):
            raise FeatureError(f"resolution={resolution!r} must be (W, H) positive integers")
        resolution = (int(resolution[0]), int(resolution[1]))
    folder = feature_dir(scene_path, model)
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:  # fail before the work
        raise FeatureError(f"features for model {model!r} already exist in {folder}: pass "
                           "--overwrite (overwrite=True) to replace them, or delete the folder")
    extractor = _EXTRACTORS[model](model, dict(options))
    scene = load_scene(scene_path, downscale=downscale, holdout_every=0)

    extra = {"extractor": "cusgs_jax.extract", "downscale": downscale,
             "options": {k: v for k, v in getattr(extractor, "opts", {}).items()
                         if k not in ("weights", "device")},
             "image_size": [scene.width, scene.height]}
    writer = FeatureWriter(scene.path, model, source=extractor.source, dtype=dtype,
                           overwrite=overwrite, extra_meta=json.loads(json.dumps(extra)))
    busy, valid, total, shape = 0.0, 0, 0, None
    with writer:
        for i in tqdm(range(scene.num_images), desc=f"cusgs-extract {model}", unit="view",
                      disable=not progress, file=sys.stderr):
            view = _View(scene.path, scene.names[i], scene.images[i])
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


def ensure_extracted(scene_path: str | os.PathLike, model: str, **kwargs) -> bool:
    """Extract ``model``'s features unless a complete set (``meta.json``) is already there.

    Safe when several processes ask at once (the jobs of a parallel sweep on one
    scene): they serialise on a lock file beside the model folder, and the ones
    that wait find the finished set and return. A folder without ``meta.json``
    is an interrupted extraction and is replaced.

    Args:
      scene_path, model, **kwargs: as :func:`extract` (``overwrite`` is decided here).
    Returns:
      True when this call extracted, False when the features were already there.
    """
    kwargs.pop("overwrite", None)
    meta = feature_dir(scene_path, model) / META_FILE
    if meta.is_file():
        return False
    with _model_lock(scene_path, model):
        if meta.is_file():  # another process finished while we waited
            return False
        extract(scene_path, model, overwrite=True, **kwargs)
    return True


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-extract SCENE --model daisy|hog|gabor|semantic|clip|dinov2
    [--resolution W H] [--lab] [--overwrite] [--dtype float16|float32] [--downscale D]
    [--weights PATH] [--arch ViT-B-16] [--dim 16] [--device cpu] [--quiet]``."""
    ap = argparse.ArgumentParser(
        prog="cusgs-extract",
        description="Extract dense per-view feature maps into SCENE/features/MODEL/ "
                    "(one .npy per image + meta.json).")
    ap.add_argument("scene", help="scene folder with images/ and sparse/0/")
    ap.add_argument("--model", required=True, choices=MODELS)
    ap.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=None,
                    help="feature map size (default: the image size; clip/dinov2: patch grid)")
    ap.add_argument("--lab", action="store_true",
                    help="daisy/hog/gabor: describe each CIE-Lab channel (3x the dimension)")
    ap.add_argument("--overwrite", action="store_true", help="replace existing features")
    ap.add_argument("--dtype", choices=("float16", "float32"), default="float16")
    ap.add_argument("--downscale", type=int, default=1, help="load images at 1/D resolution")
    ap.add_argument("--dim", type=int, default=None, help="semantic: vector dimension (32)")
    ap.add_argument("--weights", default=None,
                    help="clip/dinov2: LOCAL weights (file for clip, HF snapshot folder for "
                         "dinov2); nothing is downloaded")
    ap.add_argument("--arch", default=None, help="clip: open_clip architecture (ViT-B-16)")
    ap.add_argument("--device", default=None, help="clip/dinov2: torch device (cpu)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)

    options: dict[str, Any] = {}
    if args.lab:
        if args.model not in ("daisy", "hog", "gabor"):
            ap.error(f"--lab applies to daisy, hog and gabor, not {args.model}")
        options["lab"] = True
    for key in ("dim", "weights", "arch", "device"):
        if getattr(args, key) is not None:
            options[key] = getattr(args, key)
    try:
        s = extract(args.scene, args.model, resolution=args.resolution, downscale=args.downscale,
                    dtype=args.dtype, overwrite=args.overwrite, progress=not args.quiet,
                    **options)
    except SceneError as e:
        ap.exit(1, f"cusgs-extract: error: {e}\n")
    print(f"{s.model} features -> {s.folder}\n"
          f"  {s.num_views} views, {s.resolution[0]}x{s.resolution[1]}x{s.dim} {s.dtype}, "
          f"{100 * s.valid_fraction:.1f}% pixels with a target\n"
          f"  {1000 * s.seconds_per_view:.1f} ms/view, {s.seconds:.2f} s total")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
