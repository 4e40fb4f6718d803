"""Timing shared by the benchmark scripts."""

from __future__ import annotations

import time

import jax
import numpy as np


def median_seconds(fn, args, repeats: int) -> float:
    """Median wall seconds of ``fn(*args)`` over ``repeats`` calls, each to ``block_until_ready``
    (compile first: the calls are timed as they come)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times))
