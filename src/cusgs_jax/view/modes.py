"""What the viewer shows (functional core, NumPy only): one rendered view → an [H, W, 3] uint8 picture.

Modes (:func:`mode_names`): ``RGB``, ``depth`` (expected camera depth Σ z α T / α through the turbo
colour map, near = warm), ``alpha`` (1 − T as grey), and for each feature model ``PCA <model>``
(its rendered features through a 3-component PCA fitted on the view itself,
:func:`cusgs_jax.eval.feature_metrics.pca_rgb`) and ``query <model>`` (the cosine-similarity
heatmap of a query feature against the rendered view, thresholded with Otsu exactly as the
retrieval metric does, :func:`cusgs_jax.eval.feature_metrics.similarity_mask`).

Naming: H×W image, D feature dimension.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cusgs_jax.eval.feature_metrics import pca_rgb, similarity_mask

__all__ = ["Frame", "mode_names", "feature_of_mode", "colourise", "depth_colours", "alpha_grey", "pca_colours",
           "query_heatmap", "pixel_at"]

BASE_MODES = ("RGB", "depth", "alpha")
ALPHA_EPS = 1e-3
"""Pixels with α below this have no surface: black in depth, no part in the PCA fit or the Otsu threshold."""


@dataclasses.dataclass(frozen=True)
class Frame:
    """One rendered view (host arrays).

    Attributes:
      rgb: [H, W, 3] float32 in [0, 1]; depth: [H, W] Σ z α T; alpha: [H, W] 1 − T.
      features: {model: [H, W, D] float32} (empty when the mode needed none).
    """

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    features: dict


def mode_names(feature_models) -> list[str]:
    """The viewer's modes: RGB, depth, alpha, then ``PCA <m>`` and ``query <m>`` for each feature model."""
    models = list(feature_models)
    return [*BASE_MODES, *(f"PCA {m}" for m in models), *(f"query {m}" for m in models)]


def feature_of_mode(mode: str) -> str | None:
    """The feature model a mode shows (``PCA daisy`` → ``daisy``), or None for RGB/depth/alpha."""
    kind, _, model = mode.partition(" ")
    return model if kind in ("PCA", "query") and model else None


def _uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def _turbo(x: np.ndarray) -> np.ndarray:
    """[...] in [0, 1] → [..., 3] float in [0, 1] (matplotlib's turbo)."""
    from matplotlib import colormaps

    return colormaps["turbo"](np.clip(x, 0.0, 1.0))[..., :3]


def alpha_grey(alpha: np.ndarray) -> np.ndarray:
    """[H, W] α → [H, W, 3] uint8 grey (white = opaque)."""
    return np.repeat(_uint8(np.asarray(alpha, np.float32))[..., None], 3, axis=-1)


def depth_colours(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """[H, W] alpha-weighted depth and α → [H, W, 3] uint8: expected depth Σ z α T / α, turbo map.

    Near and far are the 2nd and 98th percentiles of the covered pixels' depths (α ≥ ALPHA_EPS), so
    one stray Gaussian does not flatten the picture; near is red, far is blue; uncovered pixels black.
    """
    alpha = np.asarray(alpha, np.float32)
    covered = alpha >= ALPHA_EPS
    out = np.zeros((*alpha.shape, 3), np.uint8)
    if not covered.any():
        return out
    z = np.asarray(depth, np.float32)[covered] / alpha[covered]
    near, far = np.percentile(z, (2.0, 98.0))
    t = (z - near) / max(float(far - near), 1e-12)
    out[covered] = _uint8(_turbo(1.0 - t))
    return out


PCA_FIT_PIXELS = 8192  # pixels the per-frame PCA is fitted on (evenly strided over the covered ones)


def pca_colours(features: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """[H, W, D] features → [H, W, 3] uint8 false colours (PCA fitted on the view's covered pixels)."""
    features = np.asarray(features, np.float32)
    fit = features if alpha is None else features[np.asarray(alpha) >= ALPHA_EPS]
    fit = fit.reshape(-1, features.shape[-1])
    if fit.shape[0] > PCA_FIT_PIXELS:  # an evenly strided subset: the basis of 300k pixels costs seconds
        fit = fit[np.linspace(0, fit.shape[0] - 1, PCA_FIT_PIXELS).astype(np.int64)]
    if not np.any(fit != 0):
        return np.zeros((*features.shape[:2], 3), np.uint8)
    return pca_rgb([features], fit_on=fit)[0]


def query_heatmap(features: np.ndarray, query: np.ndarray, rgb: np.ndarray,
                  alpha: np.ndarray | None = None) -> tuple[np.ndarray, float | None, float]:
    """The cosine-similarity heatmap of ``query`` [D] against ``features`` [H, W, D].

    The scores are thresholded with Otsu over the covered pixels
    (:func:`cusgs_jax.eval.feature_metrics.similarity_mask`, the retrieval metric's rule). Pixels in
    the mask show the turbo colour of their score (scores mapped from [min, max] of the view);
    the others show the RGB render darkened to a third, so the retrieved region stands out.

    Returns:
      (picture [H, W, 3] uint8, Otsu threshold or None when the scores are constant, fraction of
      the covered pixels in the mask).
    """
    valid = None if alpha is None else np.asarray(alpha) >= ALPHA_EPS
    scores, thr, mask = similarity_mask(features, query, valid)
    lo, hi = float(scores.min()), float(scores.max())
    heat = _turbo((scores - lo) / max(hi - lo, 1e-12))
    dim = 0.33 * np.asarray(rgb, np.float32)
    picture = np.where(mask[..., None], heat, dim)
    covered = mask.size if valid is None else max(int(valid.sum()), 1)
    return _uint8(picture), thr, float(mask.sum()) / covered


def pixel_at(screen_pos, width: int, height: int) -> tuple[int, int]:
    """Normalised screen position (x, y) in [0, 1] (0, 0 = upper left) → (row, column) of a W×H image."""
    x, y = float(screen_pos[0]), float(screen_pos[1])
    col = int(np.clip(np.floor(x * width), 0, width - 1))
    row = int(np.clip(np.floor(y * height), 0, height - 1))
    return row, col


def colourise(mode: str, frame: Frame, query: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """The picture of ``mode`` for ``frame``: ([H, W, 3] uint8, a one-line note for the panel).

    ``query`` [D] is the query feature of a ``query <model>`` mode; without one that mode shows
    the model's PCA colours and says how to make a query.
    """
    if mode == "RGB":
        return _uint8(frame.rgb), ""
    if mode == "depth":
        return depth_colours(frame.depth, frame.alpha), "expected depth: red near, blue far"
    if mode == "alpha":
        return alpha_grey(frame.alpha), "accumulated opacity 1 − T"
    model = feature_of_mode(mode)
    if model is None or model not in frame.features:
        raise ValueError(f"unknown mode {mode!r}")
    features = frame.features[model]
    if mode.startswith("PCA ") or query is None:
        note = "" if mode.startswith("PCA ") else "click a pixel (or type a text query) to search for it"
        return pca_colours(features, frame.alpha), note
    picture, thr, share = query_heatmap(features, query, frame.rgb, frame.alpha)
    note = ("scores are constant: nothing to threshold" if thr is None
            else f"Otsu threshold {thr:.3f}: {100 * share:.1f}% of the view retrieved")
    return picture, note
