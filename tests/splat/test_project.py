"""Projection against the float64 reference; quaternion and transform helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.splat.project import normalize_quats, project_gaussians, quats_to_rotmats, world_to_camera
from cusgs_jax.testing.splat_reference import project_reference
from cusgs_jax.testing.scenes import as_dtype, make_scene


@pytest.mark.parametrize("antialiased", [False, True])
def test_projection_matches_reference(antialiased):
    scene = as_dtype(make_scene(0, num=300, behind=10, offscreen=10), np.float32)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "viewmat", "K")]
    proj = project_gaussians(*map(jnp.asarray, args), scene["width"], scene["height"], antialiased=antialiased)
    ref = project_reference(*(np.asarray(a, np.float64) for a in args), scene["width"], scene["height"],
                            antialiased=antialiased)
    vis = ref["visible"]
    np.testing.assert_array_equal(proj.visible, vis)
    np.testing.assert_allclose(np.asarray(proj.means2d)[vis], ref["means2d"][vis], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(proj.conics)[vis], ref["conics"][vis], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(np.asarray(proj.opacities)[vis], ref["opacities_eff"][vis], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(proj.radii), ref["radii"])
    np.testing.assert_allclose(proj.depths, ref["depths"], rtol=1e-6)


def test_normalize_quats_degenerate_and_scaled():
    q = jnp.array([[0.0, 0, 0, 0], [1e-20, 2e-20, 0, 0], [1e20, 0, 3e20, 0], [2.0, 0, 0, 0], [jnp.inf, 0, 0, 0]])
    n = np.asarray(normalize_quats(q))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(n[0], [1, 0, 0, 0])
    np.testing.assert_allclose(n[1], np.array([1, 2, 0, 0]) / np.sqrt(5), rtol=1e-6)
    np.testing.assert_allclose(n[4], [1, 0, 0, 0])
    g = jax.grad(lambda q: jnp.sum(normalize_quats(q) * jnp.arange(4.0)))(q[:4])
    assert np.isfinite(np.asarray(g)).all()


def test_rotmats_are_orthonormal():
    q = normalize_quats(jnp.asarray(np.random.default_rng(0).normal(size=(50, 4)), jnp.float32))
    r = np.asarray(quats_to_rotmats(q), np.float64)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-6)


def test_world_to_camera_is_compensated_far_from_origin():
    rng = np.random.default_rng(0)
    angle = 0.7
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    center = np.array([1e4, -1e4, 1e4])
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ center
    means = (center + rng.uniform(-1, 1, (100, 3))).astype(np.float32)
    view32 = view.astype(np.float32)
    exact = means.astype(np.float64) @ view32[:3, :3].astype(np.float64).T + view32[:3, 3].astype(np.float64)
    ours = np.asarray(world_to_camera(jnp.asarray(means), jnp.asarray(view32)))
    naive = means @ view32[:3, :3].T + view32[:3, 3]
    err_ours = np.abs(ours - exact).max()
    err_naive = np.abs(naive - exact).max()
    # Compensated: rounding of the O(1) result only (~1e-7); naive: ulp(1e4) ≈ 1e-3.
    assert err_ours < 1e-6 < 1e-4 < err_naive
    # Its derivative is the plain one.
    jac = jax.jacfwd(lambda m: world_to_camera(m, jnp.asarray(view32)))(jnp.asarray(means[:2]))
    np.testing.assert_allclose(np.asarray(jac)[0, :, 0, :], view32[:3, :3], rtol=1e-6)


def _lens_case(model, scene):
    """(Lens, reference lens tuple) of COLMAP ``model`` with the scene's K, trusted box from data.lenses."""
    import pycolmap

    from cusgs_jax.data.lenses import lens_of_camera
    from cusgs_jax.splat.lens import Lens

    K = scene["K"]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    params = {"SIMPLE_RADIAL": [fx, cx, cy, 0.08], "RADIAL": [fx, cx, cy, -0.1, 0.02],
              "OPENCV": [fx, fy, cx, cy, -0.12, 0.02, 0.004, -0.006],
              "OPENCV_FISHEYE": [fx, fy, cx, cy, 0.05, -0.01, 0.003, -0.001]}[model]
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        scene["K"] = K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])
    camera = pycolmap.Camera(model=model, width=scene["width"], height=scene["height"], params=params)
    coeffs, bounds, fisheye = lens_of_camera(camera, "test camera")
    return Lens(jnp.asarray(coeffs, jnp.float32), jnp.asarray(bounds, jnp.float32), fisheye), (coeffs, bounds, fisheye)


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE"])
def test_projection_through_a_lens_matches_reference(model):
    scene = make_scene(3, num=300, behind=10, offscreen=10)
    lens, ref_lens = _lens_case(model, scene)
    scene = as_dtype(scene, np.float32)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "viewmat", "K")]
    proj = project_gaussians(*map(jnp.asarray, args), scene["width"], scene["height"], lens=lens)
    ref = project_reference(*(np.asarray(a, np.float64) for a in args), scene["width"], scene["height"],
                            lens=ref_lens)
    vis = ref["visible"]
    assert not vis[:20].any() and vis.sum() > 200  # behind, far off-axis (outside the trusted box) culled
    np.testing.assert_array_equal(proj.visible, vis)
    np.testing.assert_allclose(np.asarray(proj.means2d)[vis], ref["means2d"][vis], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(proj.conics)[vis], ref["conics"][vis], rtol=1e-4, atol=1e-7)
    # radii are ceil()-ed: a float32 rounding may cross an integer
    assert np.abs(np.asarray(proj.radii) - ref["radii"]).max() <= 1


def test_projection_through_a_zero_lens_is_the_pinhole_projection():
    from cusgs_jax.splat.lens import Lens

    scene = as_dtype(make_scene(4, num=200), np.float32)
    args = [jnp.asarray(scene[k]) for k in ("means", "quats", "scales", "opacities", "viewmat", "K")]
    pinhole = project_gaussians(*args, scene["width"], scene["height"])
    lens = project_gaussians(*args, scene["width"], scene["height"],
                             lens=Lens(jnp.zeros(6), jnp.asarray([-1e3, 1e3, -1e3, 1e3])))
    np.testing.assert_array_equal(lens.visible, pinhole.visible)
    for a, b in zip(lens, pinhole):  # every centre is inside the clamp box, so the two paths agree
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=2e-6, atol=1e-5)


def test_centres_outside_the_trusted_box_are_culled_with_zero_gradient():
    from cusgs_jax.splat.lens import Lens

    scene = as_dtype(make_scene(5, num=50), np.float32)
    args = [jnp.asarray(scene[k]) for k in ("means", "quats", "scales", "opacities", "viewmat", "K")]
    tight = Lens(jnp.asarray([0.05, 0, 0, 0, 0, 0.0]), jnp.asarray([-0.3, 0.3, -0.3, 0.3]))
    proj = project_gaussians(*args, scene["width"], scene["height"], lens=tight)
    cam = np.asarray(scene["means"], np.float64) @ scene["viewmat"][:3, :3].T + scene["viewmat"][:3, 3]
    inside = np.all(np.abs(cam[:, :2] / cam[:, 2:]) <= 0.3, axis=-1)
    assert 0 < inside.sum() < len(inside)
    np.testing.assert_array_equal(np.asarray(proj.visible), inside & np.asarray(proj.visible))
    grad = jax.jit(jax.grad(lambda m: jnp.sum(project_gaussians(m, *args[1:], scene["width"], scene["height"],
                                                                lens=tight).means2d)))(args[0])
    assert np.all(np.asarray(grad)[~inside] == 0) and np.any(np.asarray(grad)[inside] != 0)
