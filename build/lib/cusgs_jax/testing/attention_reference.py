"""Float64 NumPy oracle of memory attention (:func:`cusgs_jax.memory.attention.attend`)."""

from __future__ import annotations

import jax
import numpy as np

from cusgs_jax.memory.attention import LOG_TEMPERATURE_CLIP

__all__ = ["attend_reference"]


def _np_normalize(x):
    """Rows scaled to unit L2 norm; zero rows stay zero."""
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(norm > 0, x / np.where(norm > 0, norm, 1.0), 0.0)


def attend_reference(params: dict, queries, bank, valid=None) -> np.ndarray:
    """Float64 NumPy :func:`~cusgs_jax.memory.attention.attend` (keys computed from the bank).

    Args:
      params: memory head; queries [..., c]; bank [S, D]; valid [S] bool or None.
    Returns:
      [..., D] float64.
    """
    p = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), params)
    q = _np_normalize(np.asarray(queries, np.float64))
    bank = np.asarray(bank, np.float64)
    keys = _np_normalize(bank @ p["key_proj"].T)
    log_t = np.clip(p["log_temperature"], -LOG_TEMPERATURE_CLIP, LOG_TEMPERATURE_CLIP)
    logits = (q @ keys.T) * np.exp(-log_t)
    valid = np.ones(bank.shape[0], bool) if valid is None else np.asarray(valid, bool)
    if not valid.any():
        return np.zeros(q.shape[:-1] + bank.shape[1:])
    logits = np.where(valid, logits, -np.inf)
    e = np.exp(logits - logits.max(axis=-1, keepdims=True))
    a = e / e.sum(axis=-1, keepdims=True)
    f = a @ bank
    ad = p["adapter"]
    if "scale" in ad:
        return f * ad["scale"] + ad["bias"]
    return f + (f @ ad["v"]) @ ad["u"].T + ad["bias"]
