"""scan.py: the running sums and maxima and first_true give jnp.cumsum's, lax.cummax's and jnp.nonzero's values."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.scan import first_true, running_max, running_sum


@pytest.mark.parametrize("n", [0, 7, 1025])
def test_running_sums_and_maxima_are_cumsum_and_cummax_bit_for_bit(n):
    rng = np.random.default_rng(n)
    x = jnp.asarray(rng.integers(-50, 1000, n).astype(np.int32))
    np.testing.assert_array_equal(jax.jit(running_sum)(x), jnp.cumsum(x))
    np.testing.assert_array_equal(jax.jit(running_max)(x), jax.lax.cummax(x) if n else x)
    mask = jnp.asarray(rng.uniform(size=n) < 0.3)
    np.testing.assert_array_equal(running_sum(mask), jnp.cumsum(mask.astype(jnp.int32)))
    grid = jnp.asarray(rng.integers(0, 9, (5, n)).astype(np.int32))
    np.testing.assert_array_equal(running_sum(grid, axis=1), jnp.cumsum(grid, axis=1))


@pytest.mark.parametrize("p", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("size", [1, 400, 2000])
def test_first_true_is_nonzero_with_a_size(p, size):
    mask = jnp.asarray(np.random.default_rng(size).uniform(size=1000) < p)
    for fill in (0, 7):
        got = first_true(mask, size, fill)
        np.testing.assert_array_equal(got, jnp.nonzero(mask, size=size, fill_value=fill)[0])
        assert got.dtype == jnp.int32 and got.shape == (size,)


def test_a_float_scan_is_refused():
    with pytest.raises(TypeError, match="integer or boolean"):
        running_sum(jnp.ones(3, jnp.float32))
