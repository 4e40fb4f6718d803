"""splat/lens.py: COLMAP's lens models against COLMAP itself and the float64 reference."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pycolmap
import pytest

from cusgs_jax.data.lenses import lens_coefficients
from cusgs_jax.splat.lens import Lens, distort, distort_with_jacobian, inside_bounds
from cusgs_jax.testing.splat_reference import distort_reference

MODELS = {  # model: params of a 64×48 camera (strong enough that every coefficient matters)
    "SIMPLE_RADIAL": [50.0, 32.0, 24.0, 0.08],
    "RADIAL": [50.0, 31.6, 24.3, -0.1, 0.02],
    "OPENCV": [50.0, 52.0, 32.3, 23.8, -0.12, 0.02, 0.004, -0.006],
    "OPENCV_FISHEYE": [40.0, 41.0, 32.0, 24.0, 0.05, -0.01, 0.003, -0.001],
}


def _camera(model):
    return pycolmap.Camera(model=model, width=64, height=48, params=MODELS[model])


def _colmap_normalised(camera, uv):
    """COLMAP's own projection of the points (u, v, 1), back in normalised coordinates."""
    pix = camera.img_from_cam(np.concatenate([uv, np.ones((len(uv), 1))], -1))
    return (pix - [camera.principal_point_x, camera.principal_point_y]) / [camera.focal_length_x,
                                                                          camera.focal_length_y]


def _uv(seed=0, num=200):
    return np.random.default_rng(seed).uniform(-0.7, 0.7, (num, 2))


def _lens(camera):
    coeffs, fisheye = lens_coefficients(camera)
    return Lens(jnp.asarray(coeffs, jnp.float32), jnp.asarray([-1e3, 1e3, -1e3, 1e3], jnp.float32), fisheye), coeffs


@pytest.mark.parametrize("model", sorted(MODELS))
def test_distortion_matches_colmap(model):
    camera = _camera(model)
    uv = _uv()
    lens, coeffs = _lens(camera)
    expected = _colmap_normalised(camera, uv)
    ours = np.asarray(distort(lens, jnp.asarray(uv, jnp.float32)))
    np.testing.assert_allclose(ours, expected, atol=2e-6)  # float32 at |uv| < 1
    reference, _ = distort_reference(coeffs, lens.fisheye, uv)
    np.testing.assert_allclose(reference, expected, atol=1e-12)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_reference_jacobian_matches_finite_differences_of_colmap(model):
    camera = _camera(model)
    uv = _uv(1, 50)
    coeffs, fisheye = lens_coefficients(camera)
    _, jac = distort_reference(coeffs, fisheye, uv)
    step = 1e-6
    for axis in range(2):
        shift = np.zeros(2)
        shift[axis] = step
        fd = (_colmap_normalised(camera, uv + shift) - _colmap_normalised(camera, uv - shift)) / (2 * step)
        np.testing.assert_allclose(jac[:, :, axis], fd, atol=1e-8)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_jax_jacobian_matches_the_reference(model):
    camera = _camera(model)
    uv = _uv(2, 50)
    lens, coeffs = _lens(camera)
    _, jac = distort_with_jacobian(lens, jnp.asarray(uv, jnp.float32))
    _, expected = distort_reference(coeffs, lens.fisheye, uv)
    np.testing.assert_allclose(np.asarray(jac), expected, atol=3e-6)


def test_fisheye_is_smooth_through_the_axis():
    lens, _ = _lens(_camera("OPENCV_FISHEYE"))
    uv = jnp.asarray([[0.0, 0.0], [1e-5, -2e-5], [3e-3, 1e-3]], jnp.float32)
    out, jac = distort_with_jacobian(lens, uv)
    np.testing.assert_allclose(out[:2], uv[:2], atol=1e-9)
    np.testing.assert_allclose(jac[0], np.eye(2), atol=1e-6)  # D = identity to first order at the axis
    grad = jax.grad(lambda p: jnp.sum(distort_with_jacobian(lens, p)[1] ** 2))(uv)
    assert np.all(np.isfinite(np.asarray(grad)))


def test_zero_coefficients_are_the_pinhole():
    lens = Lens(jnp.zeros(6), jnp.asarray([-1.0, 1.0, -1.0, 1.0]))
    uv = jnp.asarray(_uv(3, 20), jnp.float32)
    out, jac = distort_with_jacobian(lens, uv)
    np.testing.assert_array_equal(out, uv)
    np.testing.assert_array_equal(jac, np.broadcast_to(np.eye(2), (20, 2, 2)))


def test_inside_bounds():
    lens = Lens(jnp.zeros(6), jnp.asarray([-1.0, 2.0, -0.5, 0.5]))
    uv = jnp.asarray([[0.0, 0.0], [1.9, 0.4], [2.1, 0.0], [0.0, -0.6], [-1.0, 0.5], [jnp.nan, 0.0]])
    np.testing.assert_array_equal(inside_bounds(lens, uv), [True, True, False, False, True, False])
