"""Plain greedy PSC scan: the definition :func:`cusgs_jax.memory.psc.build` must equal exactly.

Self-contained on purpose: it imports nothing from :mod:`cusgs_jax.memory.psc` (the module it
checks), so a bug in a shared helper there (the float32 cast, the cosine, the argument checks)
cannot hide by being on both sides of the comparison. Plain float64 NumPy and ``math.fsum``,
one cosine per (row, kept entry) pair, no chunks, no screening.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["ReferenceBank", "build_reference", "reference_cosine"]


@dataclasses.dataclass(frozen=True, eq=False)
class ReferenceBank:
    """The oracle's result, with the fields of :class:`cusgs_jax.memory.psc.PSCBank` the tests compare."""

    entries: np.ndarray  # [M, D] float32, the kept rows as cast to float32, in scan order
    count: int
    gamma: float
    indices: np.ndarray  # [M] int64 rows of the flattened input
    truncated: bool


def reference_cosine(a: np.ndarray, b: np.ndarray) -> float:
    """``<a,b> / sqrt(<a,a> <b,b>)`` of two float32 rows [D], each dot product the correctly rounded float64
    value of the exact sum (float32 products are exact in float64; ``math.fsum`` rounds their sum once)."""
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ab = math.fsum((a64 * b64).tolist())
    aa = math.fsum((a64 * a64).tolist())
    bb = math.fsum((b64 * b64).tolist())
    return ab / math.sqrt(aa * bb)


def build_reference(features, gamma: float, *, max_entries: int | None = None) -> ReferenceBank:
    """Plain greedy PSC scan, one :func:`reference_cosine` per (row, kept entry).

    Args:
      features: [..., D] feature vectors (flattened to [M, D] in C order), any float dtype;
        cast to float32 first (the bank's dtype), all-zero rows skipped.
      gamma: cosine threshold; a row is kept iff its cosine to every kept entry is < gamma.
      max_entries: stop when a row would become entry number ``max_entries + 1``.
    Returns:
      ReferenceBank with entries [S, D] float32.
    """
    gamma = float(gamma)
    if math.isnan(gamma):
        raise ValueError("gamma is NaN")
    x = np.asarray(features)
    x = x.reshape(-1, x.shape[-1])
    with np.errstate(over="ignore"):
        x = x.astype(np.float32)
    if not np.all(np.isfinite(x)):
        raise ValueError("features contain non-finite values (after the cast to float32)")
    kept: list[int] = []
    truncated = False
    for r in range(x.shape[0]):
        row = x[r]
        if not np.any(row):
            continue
        if any(reference_cosine(row, x[k]) >= gamma for k in kept):
            continue
        if max_entries is not None and len(kept) >= max_entries:
            truncated = True
            break
        kept.append(r)
    idx = np.asarray(kept, np.int64)
    return ReferenceBank(entries=x[idx].reshape(len(kept), x.shape[1]), count=len(kept), gamma=gamma,
                         indices=idx, truncated=truncated)
