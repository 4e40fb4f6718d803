"""Running sums and maxima of integer arrays, and the first ``size`` True entries of a mask — as the step needs them.

On a CPU backend XLA runs ``jnp.cumsum`` and ``jax.lax.cummax`` as a reduce-window over the whole axis, and
``jnp.nonzero(..., size=...)`` adds two of them; a parallel prefix (``jax.lax.associative_scan``, Blelloch's
work-efficient scan) is faster on the step's sizes (``benchmarks/scan_bench.py`` measures both) and, for
integers, gives the same values bit for bit. These helpers take integer or boolean inputs only (a float scan's rounding would
depend on the order of the additions).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _integer(x: jax.Array) -> jax.Array:
    x = jnp.asarray(x)
    if x.dtype == jnp.bool_:
        return x.astype(jnp.int32)
    if not jnp.issubdtype(x.dtype, jnp.integer):
        raise TypeError(f"an integer or boolean array is needed, not {x.dtype}: a float scan's rounding depends "
                        "on its order (use jnp.cumsum)")
    return x


def running_sum(x: jax.Array, axis: int = 0) -> jax.Array:
    """Inclusive running sum of integer ``x`` along ``axis`` (``jnp.cumsum``'s values; booleans count as int32)."""
    x = _integer(x)
    if x.shape[axis] == 0:
        return x
    return jax.lax.associative_scan(jnp.add, x, axis=axis)


def running_max(x: jax.Array, axis: int = 0) -> jax.Array:
    """Inclusive running maximum of integer ``x`` along ``axis`` (``jax.lax.cummax``'s values)."""
    x = _integer(x)
    if x.shape[axis] == 0:
        return x
    return jax.lax.associative_scan(jnp.maximum, x, axis=axis)


def first_true(mask: jax.Array, size: int, fill_value: int = 0) -> jax.Array:
    """[size] int32: the indices of the first ``size`` True entries of the 1-D ``mask``, in order, padded with
    ``fill_value`` — ``jnp.nonzero(mask, size=size, fill_value=fill_value)[0]`` — from one running sum and one
    scatter of distinct indices."""
    mask = jnp.asarray(mask, bool)
    num = mask.shape[0]
    rank = running_sum(mask) - 1  # [n] place among the True entries
    target = jnp.where(mask & (rank < size), rank, size)  # size: dropped
    out = jnp.full((size,), fill_value, jnp.int32)
    return out.at[target].set(jnp.arange(num, dtype=jnp.int32), mode="drop", unique_indices=True)
