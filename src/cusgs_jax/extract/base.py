"""What every extractor shares: the model names, the view handed over, resizing, options.

Kept apart from :mod:`.scene` (the registry and the loop over a scene) so that the optional
:mod:`.pretrained` extractors can use it without importing the registry back.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from cusgs_jax.data.features import FeatureError

__all__ = ["BUILT_IN_EXTRACTORS", "MODELS", "View", "fit_aspect", "pop_options", "resized_image"]

# Offline and deterministic, extracted automatically when a run needs them: the weight-free
# descriptors and vgg16 (ImageNet VGG16 in JAX on the weights of the lpips extra).
BUILT_IN_EXTRACTORS = ("daisy", "hog", "gabor", "semantic", "vgg16")
MODELS = BUILT_IN_EXTRACTORS + ("clip", "dinov2")


@dataclasses.dataclass(frozen=True)
class View:
    """One image handed to an extractor: its scene folder, COLMAP name and pixels, and the folder of the
    demo scene's per-pixel maps (``object_ids/``) in the frame of those pixels."""

    scene: pathlib.Path
    name: str
    image: np.ndarray  # [H, W, 3] uint8 at the loaded resolution
    maps: pathlib.Path | None = None  # default: ``scene`` (the lens demo's masked/ for data.undistort=mask)

    @property
    def maps_folder(self) -> pathlib.Path:
        return self.scene if self.maps is None else self.maps


def resized_image(image: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """[H, W, 3] uint8 → [h, w, 3] float in [0, 1] (anti-aliased resize when size=(w, h))."""
    from skimage import transform, util

    img = util.img_as_float(image)
    if size is None or (img.shape[1], img.shape[0]) == tuple(size):
        return img
    w, h = size
    return np.clip(transform.resize(img, (h, w, 3), order=1, anti_aliasing=True), 0.0, 1.0)


def fit_aspect(width: int, height: int, scale: float, tolerance: float = 0.02) -> tuple[int, int]:
    """Map size (w, h) ≈ (W, H)·``scale``, rounded, covering an image of ``width``×``height``.

    When rounding would change the aspect ratio by more than ``tolerance`` (tiny images: 40×30 at
    1/4 would be 10×8), the map is made 2×, 4×, … denser until it does not, at most the image size
    (40×30 at 1/4 → 20×15). Feature maps must keep the image's aspect (``load_features`` allows 5 %).
    """
    while True:
        w, h = max(1, round(width * scale)), max(1, round(height * scale))
        if scale >= 1.0 or abs((w / h) / (width / height) - 1.0) <= tolerance:
            return w, h
        scale = min(2.0 * scale, 1.0)


def pop_options(model: str, options: dict, allowed: dict) -> dict:
    """``allowed`` (option → default) updated with ``options``; FeatureError on unknown keys."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise FeatureError(f"option(s) {', '.join(unknown)} not supported by model {model!r}; "
                           f"it accepts: {', '.join(sorted(allowed)) or 'none'}")
    return {**allowed, **options}
