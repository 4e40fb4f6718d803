"""Plain-JAX multilayer perceptrons shared by the anchor decoder and the query heads."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from cusgs_jax.precision import HIGHEST


@functools.partial(jax.jit, static_argnums=1)
def init_mlp(key: jax.Array, sizes: tuple[int, ...]) -> dict:
    """Dense layers initialised like PyTorch ``nn.Linear`` (U(±1/√fan_in)); one program per ``sizes`` (a tuple),
    drawing the same values as its layers drawn one call at a time (``tests/test_nn.py``).

    Returns:
      {"w0": [sizes[0], sizes[1]], "b0": [sizes[1]], "w1": …}.
    """
    params = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        key, kw, kb = jax.random.split(key, 3)
        bound = 1.0 / math.sqrt(fan_in)
        params[f"w{i}"] = jax.random.uniform(kw, (fan_in, fan_out), jnp.float32, -bound, bound)
        params[f"b{i}"] = jax.random.uniform(kb, (fan_out,), jnp.float32, -bound, bound)
    return params


def apply_mlp(params: dict, x: jax.Array, precision: jax.lax.Precision = HIGHEST) -> jax.Array:
    """Dense → ReLU → … → Dense (no final activation). x: [..., sizes[0]].

    ``precision``: of the matmuls (:mod:`cusgs_jax.precision`; ``model.matmul_precision`` in a run).
    """
    layers = len(params) // 2
    for i in range(layers):
        x = jnp.matmul(x, params[f"w{i}"], precision=precision) + params[f"b{i}"]
        if i < layers - 1:
            x = jax.nn.relu(x)
    return x
