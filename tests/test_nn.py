"""nn.py: the MLPs — PyTorch's nn.Linear initialisation drawn in one program with the values of layer-by-layer
draws, and the forward pass against a float64 NumPy reference."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.nn import apply_mlp, init_mlp


def test_the_one_program_draws_bit_for_bit_what_separate_draws_give(compiles):
    # the demo run's heads (latent 32 + 3 (+ appearance 32), hidden 32, N = 10, 3 feature models of 16 query
    # channels: opacity, cov, color, query voxel, query gaussian) and an odd one
    shapes = [(35, 32, 10), (35, 32, 70), (67, 32, 30), (67, 32, 48), (51, 48), (7, 5, 3)]
    init_mlp.clear_cache()  # other tests of this process may have compiled these shapes
    for seed in range(5):
        for sizes in shapes:
            key = jax.random.PRNGKey(seed)
            got, want = init_mlp(key, sizes), init_mlp.__wrapped__(key, sizes)  # the same code, one eager call at a time
            assert sorted(got) == sorted(want)
            for name in want:
                assert got[name].shape == want[name].shape and got[name].dtype == jnp.float32
                np.testing.assert_array_equal(got[name], want[name], err_msg=f"{sizes} {name}")
    assert compiles.count(init_mlp) == len(shapes)  # one program per shape tuple, whatever the key


def test_weights_lie_within_the_fan_in_bound_and_the_forward_pass_matches_float64():
    sizes = (6, 9, 4)
    params = init_mlp(jax.random.PRNGKey(3), sizes)
    for i, fan_in in enumerate(sizes[:-1]):
        bound = 1.0 / math.sqrt(fan_in)
        assert np.all(np.abs(np.asarray(params[f"w{i}"])) <= bound) and np.all(np.abs(np.asarray(params[f"b{i}"])) <= bound)
    x = np.random.default_rng(0).normal(size=(5, 6))
    w = {k: np.asarray(v, np.float64) for k, v in params.items()}
    want = np.maximum(x @ w["w0"] + w["b0"], 0.0) @ w["w1"] + w["b1"]
    np.testing.assert_allclose(apply_mlp(params, jnp.asarray(x, jnp.float32)), want, rtol=1e-5, atol=1e-6)
