"""Float64 NumPy oracle of feature-aware pruning's significance scores.

:func:`significance_reference` is the plain-loop definition of what the jitted statistics
accumulation (one call per rendered view) followed by the anchor scoring computes:
``S_v = λ_n ‖z_v‖ + λ_g g_v + S_v^contrib / mean_{alive u} S_u^contrib``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from fractions import Fraction
from typing import Any

import numpy as np

__all__ = ["significance_reference"]


def significance_reference(latent: np.ndarray, alive: np.ndarray, views: Iterable[Mapping[str, Any]],
                           cfg) -> np.ndarray:
    """Plain NumPy float64 reference of the prune statistics' accumulation + anchor scores.

    Loops over views, slots and Gaussians; V_ref is LightGaussian's
    ``sorted(volume, descending)[int(len · p/100)]`` over the view's active
    Gaussians (clamped to the last entry).

    Args:
      latent: [A, F].
      alive: [A] bool.
      views: per view a mapping with ``slots`` [S], ``valid`` [S],
        ``latent_grad`` [S, F], ``significance`` [S·N], ``scales`` [S·N, 3],
        ``active`` [S·N] and optionally ``enabled`` (default True); S visible slots,
        N Gaussians per anchor (:mod:`cusgs_jax.types`).
      cfg: the pruning configuration; only its ``volume_percentile``, ``volume_power``,
        ``lambda_norm`` and ``lambda_grad`` attributes are read.
    Returns:
      [A] float64 scores, +inf for dead slots.
    """
    latent = np.asarray(latent, np.float64)
    alive = np.asarray(alive, bool)
    capacity = latent.shape[0]
    grad_sum = np.zeros(capacity)
    count = np.zeros(capacity)
    contrib = np.zeros(capacity)
    for view in views:
        if not view.get("enabled", True):
            continue
        slots, valid = np.asarray(view["slots"]), np.asarray(view["valid"], bool)
        sig = np.asarray(view["significance"], np.float64)
        scales = np.asarray(view["scales"], np.float64)
        n = sig.shape[0] // len(slots)
        on = np.asarray(view["active"], bool) & np.repeat(valid, n)
        volumes = [float(np.prod(scales[i])) for i in range(len(sig)) if on[i]]
        v_ref = 1.0
        if volumes:
            ordered = sorted(volumes, reverse=True)
            index = min(math.floor(Fraction(cfg.volume_percentile) / 100 * len(ordered)), len(ordered) - 1)
            v_ref = ordered[index] if ordered[index] > 0 else 1.0
        for j, slot in enumerate(slots):
            if not valid[j]:
                continue
            grad_sum[slot] += float(np.sqrt(np.sum(np.asarray(view["latent_grad"][j], np.float64) ** 2)))
            count[slot] += 1
            for i in range(j * n, (j + 1) * n):
                if on[i]:
                    contrib[slot] += sig[i] * (np.prod(scales[i]) / v_ref) ** cfg.volume_power
    grad = np.where(count > 0, grad_sum / np.maximum(count, 1), 0.0)
    mean = contrib[alive].mean() if alive.any() else 0.0
    contrib_term = contrib / mean if mean > 0 else np.zeros(capacity)
    score = cfg.lambda_norm * np.linalg.norm(latent, axis=-1) + cfg.lambda_grad * grad + contrib_term
    return np.where(alive, score, np.inf)
