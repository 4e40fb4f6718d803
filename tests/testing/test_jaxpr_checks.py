"""testing/jaxpr_checks.py: the program reader that tests/test_precision.py relies on must see every matmul."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cusgs_jax.testing.jaxpr_checks import dot_precisions, loose_dots


def test_the_check_sees_a_default_precision_matmul_even_inside_jit_scan_and_custom_vjp():
    @jax.custom_vjp
    def inner(a, b):
        return a @ b

    inner.defvjp(lambda a, b: (inner(a, b), (a, b)), lambda res, g: (g @ res[1].T, res[0].T @ g))

    def fn(a, b):
        carry, _ = jax.lax.scan(lambda c, _: (jnp.matmul(c, b, precision=jax.lax.Precision.HIGHEST), None), a,
                                None, length=2)
        return jax.jit(inner)(carry, b).sum()

    a = jnp.ones((3, 3))
    assert len(dot_precisions(fn, a, a)) == 2
    assert len(loose_dots(fn, a, a)) == 1  # the custom_vjp's forward, nested in jit
    assert len(loose_dots(jax.grad(fn), a, a)) >= 2  # and the backward's two


def test_where_names_the_line_of_the_library_that_wrote_the_matmul():
    from cusgs_jax.nn import apply_mlp, init_mlp

    params = init_mlp(jax.random.PRNGKey(0), (4, 8, 2))
    dots = dot_precisions(lambda x: apply_mlp(params, x, jax.lax.Precision.DEFAULT), jnp.ones((3, 4)))
    assert len(dots) == 2 and all(d.where.startswith("nn.py:") and not d.highest for d in dots)
