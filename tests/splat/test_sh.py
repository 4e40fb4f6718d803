"""splat/sh.py against the float64 closed-form reference: constants, forward, gradient, clamp."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.splat import sh
from cusgs_jax.testing.sh_reference import sh_basis_reference, sh_constants_reference, sh_to_rgb_reference


def _random(seed, degree, num=64, scale=0.4):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    coeffs = rng.normal(0.0, scale, (num, k, 3))
    dirs = rng.normal(size=(num, 3)) * rng.uniform(0.1, 10.0, (num, 1))  # any length: normalised inside
    return coeffs, dirs


def test_constants_match_closed_forms():
    ref = sh_constants_reference()
    assert sh.SH_C0 == pytest.approx(ref["C0"], abs=1e-15)
    assert sh.SH_C1 == pytest.approx(ref["C1"], abs=1e-15)
    np.testing.assert_allclose(sh.SH_C2, ref["C2"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(sh.SH_C3, ref["C3"], rtol=0, atol=1e-15)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_forward_matches_reference(x64, degree):
    coeffs, dirs = _random(degree, degree)
    got = sh.sh_to_rgb(jnp.asarray(coeffs), jnp.asarray(dirs))
    assert got.dtype == jnp.float64 and got.shape == (64, 3)
    np.testing.assert_allclose(np.asarray(got), sh_to_rgb_reference(coeffs, dirs), rtol=0, atol=1e-13)
    basis = sh.sh_basis(jnp.asarray(dirs), degree)
    np.testing.assert_allclose(np.asarray(basis), sh_basis_reference(dirs, degree), rtol=0, atol=1e-13)


def test_lower_degree_ignores_higher_coefficients(x64):
    coeffs, dirs = _random(5, 3)
    got = sh.sh_to_rgb(jnp.asarray(coeffs), jnp.asarray(dirs), degree=1)
    np.testing.assert_allclose(np.asarray(got), sh_to_rgb_reference(coeffs[:, :4], dirs), atol=1e-13)
    with pytest.raises(ValueError, match="degree"):
        sh.sh_to_rgb(jnp.asarray(coeffs[:, :4]), jnp.asarray(dirs), degree=2)
    with pytest.raises(ValueError, match="not"):
        sh.sh_to_rgb(jnp.zeros((3, 5, 3)), jnp.ones((3, 3)))


def test_broadcast_and_float32():
    coeffs, dirs = _random(6, 2, num=8)
    got = jax.jit(sh.sh_to_rgb)(jnp.asarray(coeffs[None], jnp.float32), jnp.asarray(dirs[:1], jnp.float32))
    assert got.shape == (1, 8, 3) and got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got)[0], sh_to_rgb_reference(coeffs, dirs[:1]), atol=2e-6)


def test_degree0_is_dc_term():
    f_dc = np.random.default_rng(1).normal(size=(10, 1, 3))
    dirs = np.random.default_rng(2).normal(size=(10, 3))
    got = sh.sh_to_rgb(jnp.asarray(f_dc, jnp.float32), jnp.asarray(dirs, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), np.maximum(0.0, 0.5 + 0.28209479177387814 * f_dc[:, 0]),
                               atol=1e-6)


def test_clamp_at_zero():
    coeffs = jnp.zeros((2, 4, 3)).at[:, 0, :].set(jnp.array([-5.0, 0.0, 5.0]))
    rgb = sh.sh_to_rgb(coeffs, jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    assert np.all(np.asarray(rgb[:, 0]) == 0.0) and np.all(np.asarray(rgb[:, 1]) == 0.5)
    grad = jax.grad(lambda c: sh.sh_to_rgb(c, jnp.ones((2, 3))).sum())(coeffs)
    assert np.all(np.asarray(grad[:, :, 0]) == 0.0)  # clamped channel passes no gradient
    # The zero direction is finite (normalised with a floor, as torch's F.normalize).
    g = jax.grad(lambda d: sh.sh_to_rgb(jnp.ones((4, 3)), d).sum())(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("degree", [1, 3])
def test_gradient_matches_finite_differences(x64, degree):
    coeffs, dirs = _random(10 + degree, degree, num=6, scale=1.5)
    # keep every pre-clamp value away from the kink at 0, where differences are meaningless
    raw = np.einsum("gk,gkc->gc", sh_basis_reference(dirs, degree), coeffs) + 0.5
    coeffs[:, 0, :] += np.where(np.abs(raw) < 0.05, 0.5, 0.0) / 0.28209479177387814
    assert np.any(raw < -0.05) and np.any(raw > 0.05)  # both sides of the clamp are exercised
    cot = np.random.default_rng(3).normal(size=(6, 3))

    def loss_ref(c, d):
        return float(np.sum(cot * sh_to_rgb_reference(c, d)))

    def fd(x, f, eps=1e-6):
        g = np.zeros_like(x)
        for i in np.ndindex(x.shape):
            e = np.zeros_like(x)
            e[i] = eps
            g[i] = (f(x + e) - f(x - e)) / (2 * eps)
        return g

    _, vjp = jax.vjp(sh.sh_to_rgb, jnp.asarray(coeffs), jnp.asarray(dirs))
    g_coeffs, g_dirs = vjp(jnp.asarray(cot))
    np.testing.assert_allclose(np.asarray(g_coeffs), fd(coeffs, lambda c: loss_ref(c, dirs)), atol=1e-7)
    np.testing.assert_allclose(np.asarray(g_dirs), fd(dirs, lambda d: loss_ref(coeffs, d)), atol=1e-7)
