"""Plain greedy PSC scan: the definition :func:`cusgs_jax.memory.psc.build` must equal exactly."""

from __future__ import annotations

import numpy as np

from cusgs_jax.memory.psc import PSCBank, _as_rows, _rows_f32, _validate, exact_cosine

__all__ = ["build_reference"]


def build_reference(features, gamma: float, *, max_entries: int | None = None) -> PSCBank:
    """Plain greedy PSC scan, one :func:`~cusgs_jax.memory.psc.exact_cosine` per (row, kept entry).

    Args:
      features: [..., D] feature vectors (flattened to [M, D] in C order), any float dtype.
      gamma: cosine threshold; a row is kept iff its cosine to every kept entry is < gamma.
      max_entries: stop when a row would become entry number ``max_entries + 1``.
    Returns:
      PSCBank with entries [S, D] float32.
    """
    gamma, _, max_entries = _validate(gamma, 1, max_entries)
    x = _rows_f32(_as_rows(features))
    kept: list[int] = []
    truncated = False
    for r in range(x.shape[0]):
        row = x[r]
        if not np.any(row):
            continue
        if any(exact_cosine(row, x[k]) >= gamma for k in kept):
            continue
        if max_entries is not None and len(kept) >= max_entries:
            truncated = True
            break
        kept.append(r)
    idx = np.asarray(kept, np.int64)
    return PSCBank(entries=x[idx].reshape(len(kept), x.shape[1]), count=len(kept), gamma=gamma,
                   indices=idx, truncated=truncated)
