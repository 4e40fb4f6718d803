"""Evaluation metrics: PSNR, SSIM, and a per-view aggregation helper.

``psnr`` and ``ssim`` are jittable JAX functions returning 0-d arrays;
``mean_and_per_view`` runs on the host and returns Python floats.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

from cusgs_jax.losses import masked_mean, ssim

__all__ = ["PSNR_MAX_DB", "mean_and_per_view", "psnr", "ssim"]

PSNR_MAX_DB = 100.0
"""PSNR of identical images (MSE = 0), and the cap for all others."""


def psnr(pred, target, data_range: float = 1.0, *, max_db: float = PSNR_MAX_DB, mask=None) -> jnp.ndarray:
    """Peak signal-to-noise ratio 10·log10(data_range² / MSE) in dB → 0-d array.

    Args:
      pred, target: images of equal shape (e.g. [H, W, C]); the MSE runs over all
        elements, so for a batch [V, H, W, C] this is the PSNR of the pooled MSE,
        not the mean per-view PSNR (use :func:`mean_and_per_view` for that).
      data_range: peak value R (1.0 for images in [0, 1]).
      max_db: cap. Identical images (MSE = 0) give exactly ``max_db`` (default
        100 dB) instead of inf, so means over views stay finite; any pair whose
        PSNR would exceed the cap (RMSE < 1e-5·R at 100 dB) also reads ``max_db``.
        Below the cap the value equals ``skimage.metrics.peak_signal_noise_ratio``.
      mask: optional [H, W] valid-pixel mask (bool or 0/1): the MSE runs over the valid pixels only
        (``SceneData.valid``); ``max_db`` when none is valid.
    """
    pred = jnp.asarray(pred)
    target = jnp.asarray(target)
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {pred.shape} vs {target.shape}")
    dtype = jnp.promote_types(jnp.promote_types(pred.dtype, target.dtype), jnp.float32)
    diff = pred.astype(dtype) - target.astype(dtype)
    mse = masked_mean(diff * diff, mask)
    # the two constants in NumPy (one IEEE rounding each, as XLA's x·x and x·c): no program of their own
    peak = np.asarray(data_range, dtype) * np.asarray(data_range, dtype)
    floor = peak * np.asarray(10.0 ** (-max_db / 10.0), dtype)  # the MSE at which PSNR = max_db
    return jnp.minimum(10.0 * jnp.log10(peak / jnp.maximum(mse, floor)), max_db)


def mean_and_per_view(metric: Callable, preds: Sequence, targets: Sequence) -> dict:
    """Evaluate ``metric(pred, target)`` per view and average.

    Args:
      metric: e.g. :func:`psnr` or :func:`ssim`; called on one [H, W, C] pair at a time.
      preds, targets: equal-length sequences of images, or stacked [V, H, W, C] arrays.
    Returns:
      {"mean": float, "per_view": [float] * N} — the mean is the arithmetic mean of
      the per-view values (e.g. mean PSNR in dB, as reported by 3DGS papers).
    """
    if len(preds) != len(targets):
        raise ValueError(f"{len(preds)} predictions but {len(targets)} targets")
    if len(preds) == 0:
        raise ValueError("no views to evaluate")
    per_view = [float(metric(p, t)) for p, t in zip(preds, targets)]
    return {"mean": float(np.mean(per_view)), "per_view": per_view}
