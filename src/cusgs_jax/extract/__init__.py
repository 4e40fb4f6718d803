"""Dense per-view feature maps for a scene (``cusgs-extract``: :mod:`cusgs_jax.app.extract`).

* :mod:`.descriptors` — weight-free per-image descriptors (daisy, hog, gabor, semantic):
  [H, W, 3] image (or [H, W] object ids) → [H, W, D] float32 map; NumPy / scikit-image only.
* :mod:`.vgg` — the built-in ``vgg16`` model: ImageNet VGG16 relu3_3 features in JAX on the
  ``lpips`` extra's weights (imported only when vgg16 is asked for).
* :mod:`.pretrained` — optional CLIP (open_clip) / DINOv2 (timm) patch-token extractors (local
  weights; torch is imported only when one is used).
* :mod:`.scene` — :func:`extract_scene` over every image of a loaded scene into ``<scene>/features/<model>/``
  (format of :mod:`cusgs_jax.data.features`) and the lock-protected :func:`ensure_extracted`.

Importing this package does not import JAX or torch.
"""

from cusgs_jax.extract.descriptors import (
    daisy_features,
    gabor_features,
    hog_features,
    semantic_features,
    semantic_palette,
)
from cusgs_jax.extract.scene import (
    BUILT_IN_EXTRACTORS,
    MODELS,
    ExtractSummary,
    ensure_extracted,
    extract_scene,
)

__all__ = [
    "BUILT_IN_EXTRACTORS",
    "MODELS",
    "ExtractSummary",
    "daisy_features",
    "ensure_extracted",
    "extract_scene",
    "gabor_features",
    "hog_features",
    "semantic_features",
    "semantic_palette",
]
