"""Resizing dense feature maps ([N, h, w, D] or [h, w, D]) with "no target" zero vectors kept
out of the average (re-exported by :mod:`cusgs_jax.data.features`)."""

from __future__ import annotations

import numpy as np

__all__ = ["resize_features"]


def _area_weights(src: int, dst: int) -> np.ndarray:
    """[dst, src] overlap of destination pixel i (spanning [i·s, (i+1)·s), s = src/dst, in source
    pixels) with source pixel k ([k, k+1)). Rows sum to s."""
    scale = src / dst
    lo = np.arange(dst)[:, None] * scale
    hi = lo + scale
    k = np.arange(src)[None, :]
    return np.clip(np.minimum(hi, k + 1) - np.maximum(lo, k), 0.0, None)


def resize_features(maps: np.ndarray, size: tuple[int, int], *, method: str = "area") -> np.ndarray:
    """Resize feature maps to ``size = (w2, h2)``.

    Args:
      maps: [N, h, w, D] (or [h, w, D]) feature maps; zero vectors are "no target".
      size: (w2, h2), the output width and height.
      method:
        "area" (default): each output pixel is the overlap-weighted mean of the *valid* (non-zero)
          input vectors under its footprint (exact box/area filter, like OpenCV's INTER_AREA when
          shrinking; piecewise constant with blended borders when enlarging). Zero vectors do
          not dilute their neighbours; an output pixel is zero only when no valid input overlaps
          it. Use for continuous features.
        "nearest": each output pixel copies the input pixel under its centre. Keeps vectors (and
          the zero mask) exactly; use for label-like features (e.g. "semantic").
    Returns:
      [N, h2, w2, D] float32 (or [h2, w2, D] for a 3-D input).
    """
    arr = np.asarray(maps, np.float32)
    squeeze = arr.ndim == 3
    if squeeze:
        arr = arr[None]
    if arr.ndim != 4:
        raise ValueError(f"maps must be [N, h, w, D] or [h, w, D], got shape {arr.shape}")
    w2, h2 = (int(v) for v in size)
    if w2 < 1 or h2 < 1:
        raise ValueError(f"size must be (w, h) with positive integers, got {size}")
    _, h, w, _ = arr.shape
    if (h, w) == (h2, w2):
        out = arr.copy()
    elif method == "nearest":
        rows = np.minimum(((np.arange(h2) + 0.5) * h / h2).astype(np.int64), h - 1)
        cols = np.minimum(((np.arange(w2) + 0.5) * w / w2).astype(np.int64), w - 1)
        out = arr[:, rows][:, :, cols]
    elif method == "area":
        wr = _area_weights(h, h2).astype(np.float32)
        wc = _area_weights(w, w2).astype(np.float32)
        valid = np.any(arr != 0, axis=-1).astype(np.float32)
        num = np.einsum("ik,nkld,jl->nijd", wr, arr, wc, optimize=True)
        den = np.einsum("ik,nkl,jl->nij", wr, valid, wc, optimize=True)
        out = np.where(den[..., None] > 1e-12, num / np.maximum(den, 1e-12)[..., None], 0.0)
        out = out.astype(np.float32)
    else:
        raise ValueError(f"method must be 'area' or 'nearest', got {method!r}")
    return out[0] if squeeze else out
