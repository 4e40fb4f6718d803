"""Baking a scaffold into view-independent Gaussians: SH fit, opacity and covariance choices, dropping, frames."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import DecoderConfig
from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.io import SplatModel, render_splats
from cusgs_jax.model.anchors import AnchorParams, AnchorState
from cusgs_jax.model.bake import (bake_anchors, bake_splats, fibonacci_sphere, fit_sh, matrix_to_quat, mean_covariance,
                                  mean_shape, sh_fit_matrix,
                                  to_colmap_frame)
from cusgs_jax.model.decode import init_decoder
from cusgs_jax.splat.project import normalize_quats, quats_to_rotmats
from cusgs_jax.splat.sh import sh_basis
from cusgs_jax.testing.scenes import random_rotation
from cusgs_jax.types import Camera

N, F, E, HID = 4, 8, 8, 16
CFG = DecoderConfig(n_offsets=N, latent_dim=F, hidden=HID, appearance_dim=E)


def test_fibonacci_sphere_is_unit_distinct_and_balanced():
    d = fibonacci_sphere(64)
    assert d.shape == (64, 3) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    gaps = np.linalg.norm(d[:, None] - d[None], axis=-1) + np.eye(64) * 9
    assert gaps.min() > 0.2  # evenly spread: no two directions close (uniform spacing ≈ sqrt(4π/64) ≈ 0.44)
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=0.02)
    with pytest.raises(ValueError):
        fibonacci_sphere(0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_fit_recovers_known_coefficients(degree):
    k = (degree + 1) ** 2
    rng = np.random.default_rng(degree)
    coeffs = rng.normal(0, 0.3, (50, k, 3)).astype(np.float32)
    dirs = fibonacci_sphere(64)
    basis = np.asarray(sh_basis(jnp.asarray(dirs), degree))  # [D, K]
    colors = 0.5 + np.einsum("dk,gkc->gdc", basis, coeffs)  # unclamped: exactly SH of the degree
    fitted = np.asarray(fit_sh(jnp.asarray(colors), jnp.asarray(sh_fit_matrix(dirs, degree))))
    np.testing.assert_allclose(fitted, coeffs, atol=2e-5)
    if degree < 3:  # a higher-degree fit of the same colours finds zero higher coefficients
        high = np.asarray(fit_sh(jnp.asarray(colors), jnp.asarray(sh_fit_matrix(dirs, 3))))
        np.testing.assert_allclose(high[:, :k], coeffs, atol=2e-5)
        np.testing.assert_allclose(high[:, k:], 0.0, atol=2e-5)


def _cov(quats, scales):
    rot = np.asarray(quats_to_rotmats(normalize_quats(jnp.asarray(quats))), np.float64)
    return np.einsum("...ij,...j,...kj->...ik", rot, np.asarray(scales, np.float64) ** 2, rot)


def test_mean_shape_is_exact_for_one_shape_and_ignores_zero_weights():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(7, 4)).astype(np.float32)
    s = rng.uniform(0.01, 0.2, (7, 3)).astype(np.float32)
    other_q, other_s = rng.normal(size=(7, 4)).astype(np.float32), rng.uniform(1, 2, (7, 3)).astype(np.float32)
    # [D=4, G, 4]: the same rotation with both signs and raw norms, and a direction where the Gaussian is off
    quats = np.stack([q, -3 * q, 0.5 * q, other_q])
    scales = np.stack([s, s, s, other_s])
    weights = np.array([[0.3] * 7, [0.9] * 7, [0.2] * 7, [0.0] * 7], np.float32)
    mq, ms = mean_shape(jnp.asarray(quats), jnp.asarray(scales), jnp.asarray(weights))
    np.testing.assert_allclose(np.asarray(ms), s, rtol=1e-5)
    np.testing.assert_allclose(_cov(mq, ms), _cov(q, s), rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(mq), axis=1), 1.0, atol=1e-6)
    # scales: the weighted geometric mean; all-zero weights count every direction equally
    mq, ms = mean_shape(jnp.asarray(quats[:2]), jnp.asarray(np.stack([s, 4 * s])), jnp.asarray([[1.0] * 7, [3.0] * 7]))
    np.testing.assert_allclose(np.asarray(ms), s * 4 ** 0.75, rtol=1e-5)
    _, ms = mean_shape(jnp.asarray(quats[:2]), jnp.asarray(np.stack([s, 4 * s])), jnp.zeros((2, 7)))
    np.testing.assert_allclose(np.asarray(ms), 2 * s, rtol=1e-5)



@pytest.mark.slow
def test_mean_covariance_is_the_weighted_mean_of_the_covariances():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(3, 9, 4)).astype(np.float32)
    s = rng.uniform(0.01, 0.3, (3, 9, 3)).astype(np.float32)
    w = rng.uniform(0.0, 1.0, (3, 9)).astype(np.float32)
    w[2, :4] = 0.0  # off in one view: it does not count
    mq, ms = mean_covariance(jnp.asarray(q), jnp.asarray(s), jnp.asarray(w))
    want = np.einsum("vg,vgij->gij", w / w.sum(0), _cov(q, s))
    np.testing.assert_allclose(_cov(mq, ms), want, rtol=2e-4, atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(mq), axis=1), 1.0, atol=1e-6)
    # one shape (any sign and norm of its quaternion) is kept exactly; all-zero weights count views equally
    one, _ = mean_covariance(jnp.asarray(np.stack([q[0], -2 * q[0]])), jnp.asarray(np.stack([s[0], s[0]])),
                             jnp.asarray(np.stack([w[0], 0 * w[0]])))
    np.testing.assert_allclose(_cov(one, mean_covariance(jnp.asarray(q[:1]), jnp.asarray(s[:1]),
                                                         jnp.ones((1, 9)))[1]), _cov(q[0], s[0]), rtol=2e-4,
                               atol=1e-7)  # float32 rounding on the small off-diagonal entries (seen on a GPU)
    _, equal = mean_covariance(jnp.asarray(q[:2]), jnp.asarray(s[:2]), jnp.zeros((2, 9)))
    np.testing.assert_allclose(np.sort(np.asarray(equal) ** 2, axis=1),
                               np.sort(np.linalg.eigvalsh(0.5 * (_cov(q[0], s[0]) + _cov(q[1], s[1]))), axis=1),
                               rtol=2e-4)


def test_matrix_to_quat_inverts_quats_to_rotmats_and_stays_finite_at_half_turns():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(64, 4))
    q[:8, 0] = 1e-4  # rotations by almost 180°: trace ≈ −1, the case the axis flips avoid in mean_covariance
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    back = np.asarray(matrix_to_quat(quats_to_rotmats(jnp.asarray(q))))
    keep = np.trace(np.asarray(quats_to_rotmats(jnp.asarray(q))), axis1=1, axis2=2) > -0.75
    assert np.min(np.abs(np.sum(back[keep] * q[keep], axis=1))) > 1 - 1e-5
    assert keep.sum() > 30 and np.all(np.isfinite(back))

def _anchors(num=5, seed=0):
    rng = np.random.default_rng(seed)
    params = AnchorParams(offsets=jnp.asarray(rng.normal(size=(num, N, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (num, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(num, F)), jnp.float32))
    return AnchorState(jnp.asarray(rng.uniform(-1, 1, (num, 3)), jnp.float32), jnp.ones(num, bool), params)


def _decoder(opacity_bias, color_dc=None, direction_opacity=False):
    """Random heads, with the opacity head replaced: tanh(bias) per slot, or tanh(d_z) (direction-dependent)."""
    dec = init_decoder(jax.random.PRNGKey(3), CFG)
    w0 = jnp.zeros((F + 3, HID))
    w1 = jnp.zeros((HID, N))
    if direction_opacity:  # hidden 0 = relu(d_z), hidden 1 = relu(−d_z): output d_z for every slot
        w0 = w0.at[F + 2, 0].set(1.0).at[F + 2, 1].set(-1.0)
        w1 = w1.at[0].set(1.0).at[1].set(-1.0)
    dec["opacity"] = dict(w0=w0, b0=jnp.zeros(HID), w1=w1, b1=jnp.asarray(opacity_bias, jnp.float32))
    if color_dc is not None:  # a colour that does not depend on anything: sigmoid(logit(c))
        logit = np.log(np.asarray(color_dc) / (1 - np.asarray(color_dc)))
        dec["color"] = dict(w0=jnp.zeros((F + 3 + E, HID)), b0=jnp.zeros(HID), w1=jnp.zeros((HID, 3 * N)),
                            b1=jnp.asarray(np.tile(logit, N), jnp.float32))
    return dec


def test_never_visible_gaussians_are_dropped_and_positions_are_direction_free():
    anchors = _anchors()
    bias = np.array([-0.5, 0.3, 0.004, 1.0])  # slot 0 off everywhere, slot 2 below min_opacity everywhere
    nets = {"decoder": _decoder(bias), "appearance": jnp.ones((3, E))}
    model, summary = bake_splats(anchors, nets, CFG, sh_degree=2, directions=32, min_opacity=0.005)
    assert summary.considered == 5 * N and summary.gaussians == 5 * 2 and summary.dropped_never_visible == 5 * 2
    assert model.sh.shape == (10, 9, 3) and model.quats.shape == (10, 4)
    opac = np.asarray(model.opacities).reshape(5, 2)
    np.testing.assert_allclose(opac, np.tile(np.tanh([0.3, 1.0]), (5, 1)), rtol=1e-5)
    scaling = np.exp(np.asarray(anchors.params.log_scaling))
    expected = np.asarray(anchors.centers)[:, None] + np.asarray(anchors.params.offsets) * scaling[:, None, :3]
    np.testing.assert_allclose(np.asarray(model.means).reshape(5, 2, 3), expected[:, [1, 3]], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(model.quats), axis=1), 1.0, atol=1e-5)


def test_direction_dependent_opacity_is_the_mean_over_all_directions():
    anchors = _anchors(3)
    nets = {"decoder": _decoder(np.zeros(N), direction_opacity=True)}
    cfg = DecoderConfig(n_offsets=N, latent_dim=F, hidden=HID, appearance_dim=0)
    nets["decoder"]["color"] = init_decoder(jax.random.PRNGKey(4), cfg)["color"]
    dirs = fibonacci_sphere(64)
    model, summary = bake_splats(anchors, nets, cfg, sh_degree=1, directions=64)
    assert summary.gaussians == 3 * N  # on from the half of the sphere with d_z > 0
    z = dirs[:, 2]
    expected = np.maximum(np.tanh(z), 0).mean()  # ≈ ½ ln cosh 1 = 0.217: the "off" half counts as 0
    np.testing.assert_allclose(np.asarray(model.opacities), expected, rtol=1e-5)
    assert abs(expected - 0.5 * math.log(math.cosh(1.0))) < 0.01
    baked = bake_anchors(nets["decoder"], anchors.params, anchors.centers, anchors.alive, None, jnp.asarray(dirs),
                         jnp.asarray(sh_fit_matrix(dirs, 1)), cfg)
    np.testing.assert_allclose(np.asarray(baked.on_fraction), 0.5)
    np.testing.assert_allclose(np.asarray(baked.max_opacity), np.tanh(z.max()), rtol=1e-5)


def test_with_cameras_opacity_and_shape_average_the_cameras_that_see_the_anchor():
    """tanh(d_z) opacity: a camera in front (looking +z) sees the anchors; one behind them does not count."""
    rng = np.random.default_rng(7)
    num = 4
    params = AnchorParams(offsets=jnp.asarray(rng.normal(size=(num, N, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (num, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(num, F)), jnp.float32))
    centers = np.concatenate([rng.uniform(-0.1, 0.1, (num - 1, 3)), [[100.0, 0.0, 0.0]]]).astype(np.float32)
    anchors = AnchorState(jnp.asarray(centers), jnp.ones(num, bool), params)  # the last one: seen by no camera
    cfg = DecoderConfig(n_offsets=N, latent_dim=F, hidden=HID, appearance_dim=0)
    nets = {"decoder": _decoder(np.zeros(N), direction_opacity=True)}
    nets["decoder"]["color"] = init_decoder(jax.random.PRNGKey(4), cfg)["color"]
    positions = np.array([[0.0, 0.0, -3.0], [0.0, 0.0, 3.0]])  # both look down +z: the second sees nothing
    viewmats = np.tile(np.eye(4), (2, 1, 1))
    viewmats[:, :3, 3] = -positions
    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    cams = Camera(jnp.asarray(np.stack([K, K]), jnp.float32), jnp.asarray(viewmats, jnp.float32), 32, 24)
    model, summary = bake_splats(anchors, nets, cfg, sh_degree=1, directions=16, cameras=cams)
    assert summary.cameras == 2 and summary.gaussians == num * N

    def on(camera):
        d = centers - camera
        return np.maximum(np.tanh(d[:, 2] / np.linalg.norm(d, axis=1)), 0.0)

    expected = on(positions[0])  # the front camera only
    expected[-1] = 0.5 * (on(positions[0])[-1] + on(positions[1])[-1])  # seen by none: both count
    np.testing.assert_allclose(np.asarray(model.opacities).reshape(num, N), np.repeat(expected[:, None], N, 1),
                               rtol=1e-4)
    sphere, _ = bake_splats(anchors, nets, cfg, sh_degree=1, directions=16)
    # colours: the sphere either way (bit-equal on a CPU; another program's fusion on a GPU: to rounding)
    np.testing.assert_allclose(np.asarray(model.sh), np.asarray(sphere.sh), rtol=1e-6, atol=1e-7)
    # max_cameras keeps an evenly spread subset
    _, summary = bake_splats(anchors, nets, cfg, sh_degree=1, directions=16, cameras=cams, max_cameras=1)
    assert summary.cameras == 1
    # a data.undistort=lens run's cameras: "sees" is the frustum through the lens. A trusted box that excludes the
    # anchors (0.5 ≤ x/z ≤ 0.6 while they sit within 0.1/3 of the axis) leaves every anchor seen by none: both count
    from cusgs_jax.splat.lens import Lens

    tight = Lens(jnp.zeros((2, 6)), jnp.tile(jnp.asarray([0.5, 0.6, 0.5, 0.6]), (2, 1)))
    blind, _ = bake_splats(anchors, nets, cfg, sh_degree=1, directions=16,
                           cameras=dataclasses.replace(cams, lens=tight))
    both = 0.5 * (on(positions[0]) + on(positions[1]))
    np.testing.assert_allclose(np.asarray(blind.opacities).reshape(num, N), np.repeat(both[:, None], N, 1),
                               rtol=1e-4)
    wide = Lens(jnp.zeros((2, 6)), jnp.tile(jnp.asarray([-5.0, 5.0, -5.0, 5.0]), (2, 1)))
    through, _ = bake_splats(anchors, nets, cfg, sh_degree=1, directions=16, cameras=dataclasses.replace(cams, lens=wide))
    np.testing.assert_allclose(np.asarray(through.opacities), np.asarray(model.opacities), rtol=1e-6)


def test_constant_colour_bakes_to_dc_only_with_the_mean_appearance():
    anchors = _anchors(2)
    nets = {"decoder": _decoder(np.full(N, 0.5), color_dc=[0.2, 0.5, 0.9]),
            "appearance": jnp.asarray(np.random.default_rng(0).normal(size=(4, E)), jnp.float32)}
    model, _ = bake_splats(anchors, nets, CFG, sh_degree=3, directions=64)
    sh = np.asarray(model.sh)
    np.testing.assert_allclose(0.5 + 0.28209479177387814 * sh[:, 0], np.tile([0.2, 0.5, 0.9], (2 * N, 1)), atol=1e-5)
    np.testing.assert_allclose(sh[:, 1:], 0.0, atol=1e-5)


def test_dead_anchors_and_chunking_do_not_change_the_result():
    anchors = _anchors(7)
    nets = {"decoder": init_decoder(jax.random.PRNGKey(5), CFG), "appearance": jnp.ones((2, E))}
    whole, s1 = bake_splats(anchors, nets, CFG, directions=24, sh_degree=1, chunk_anchors=64)
    parts, s2 = bake_splats(anchors, nets, CFG, directions=24, sh_degree=1, chunk_anchors=3)
    assert s1 == s2
    for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(parts)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    dead = anchors.replace(alive=anchors.alive.at[2].set(False))
    _, s3 = bake_splats(dead, nets, CFG, directions=24, sh_degree=1)
    assert s3.considered == 6 * N
    with pytest.raises(ValueError, match="directions"):
        bake_splats(anchors, nets, CFG, directions=10, sh_degree=3)


def test_colmap_frame_moves_positions_and_scales_only_and_renders_the_same():
    rng = np.random.default_rng(2)
    g = 40
    world = WorldTransform(scale=0.02, center=(300.0, -120.0, 55.0))
    model = SplatModel(means=rng.uniform(-0.3, 0.3, (g, 3)).astype(np.float32) + np.float32([0, 0, 1.5]),
                       quats=rng.normal(size=(g, 4)).astype(np.float32),
                       log_scales=rng.uniform(-4, -3, (g, 3)).astype(np.float32),
                       opacity_logits=rng.normal(size=g).astype(np.float32),
                       sh=rng.normal(0, 0.3, (g, 16, 3)).astype(np.float32))
    means, log_scales, quats, sh = to_colmap_frame(model.means, model.log_scales, model.quats, model.sh, world)
    np.testing.assert_array_equal(quats, model.quats)  # no rotation: rotations and SH colours unchanged
    np.testing.assert_array_equal(sh, model.sh)
    np.testing.assert_allclose(means, world.to_colmap(model.means))
    np.testing.assert_allclose(world.to_normalized(means), model.means, atol=1e-9)
    np.testing.assert_allclose(np.exp(log_scales), np.exp(model.log_scales.astype(np.float64)) / 0.02, rtol=1e-9)
    # the same picture from the same camera in either frame (the camera moved with world.viewmats)
    K = jnp.array([[40.0, 0, 20], [0, 40, 15], [0, 0, 1]])
    colmap_view = np.eye(4)
    colmap_view[:3, 3] = -np.asarray(world.center)  # a camera at the COLMAP centre, looking down +z
    norm_view = world.viewmats(colmap_view[None])[0]
    shift = np.asarray(world.center)  # render the COLMAP model recentred (float32 detail), as cusgs-render-ply
    moved = SplatModel(means=(means - shift).astype(np.float32), quats=model.quats,
                       log_scales=log_scales.astype(np.float32), opacity_logits=model.opacity_logits, sh=model.sh)
    colmap_cam = np.array(colmap_view)
    colmap_cam[:3, 3] += colmap_cam[:3, :3] @ shift
    a = render_splats(model, Camera(K, jnp.asarray(norm_view, jnp.float32), 40, 30), background=(0, 0, 0)).image
    b = render_splats(moved, Camera(K, jnp.asarray(colmap_cam, jnp.float32), 40, 30), background=(0, 0, 0)).image
    assert float(jnp.max(a)) > 0.05
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-4)


def test_rotated_frame_exports_rotations_and_sh_colours_that_render_the_same():
    """data.align=principal: the export undoes the frame's rotation Q too — positions, Gaussian
    rotations and view-dependent SH colours; the same camera sees the same picture in either frame."""
    from cusgs_jax.model.bake import rotate_sh

    rng = np.random.default_rng(3)
    g = 40
    q = random_rotation(3)
    world = WorldTransform(scale=0.5, center=(3.0, -1.0, 2.0), rotation=tuple(map(tuple, q)))
    model = SplatModel(means=rng.uniform(-0.3, 0.3, (g, 3)).astype(np.float32) + np.float32([0, 0, 1.5]),
                       quats=rng.normal(size=(g, 4)).astype(np.float32),
                       log_scales=np.log(rng.uniform(0.02, 0.12, (g, 3))).astype(np.float32),
                       opacity_logits=rng.normal(size=g).astype(np.float32),
                       sh=rng.normal(0, 0.3, (g, 16, 3)).astype(np.float32))
    means, log_scales, quats, sh = to_colmap_frame(model.means, model.log_scales, model.quats, model.sh, world)
    # SH: the colour along a COLMAP direction d is the trained colour along Q d
    dirs = fibonacci_sphere(50).astype(np.float64)
    np.testing.assert_allclose(np.einsum("dk,gkc->gdc", np.asarray(sh_basis(jnp.asarray(dirs), 3)), sh),
                               np.einsum("dk,gkc->gdc", np.asarray(sh_basis(jnp.asarray(dirs @ q.T), 3)),
                                         model.sh.astype(np.float64)), atol=1e-5)
    np.testing.assert_allclose(rotate_sh(rotate_sh(sh, q.T), q), sh, atol=1e-6)
    # rotations: R_colmap = Qᵀ R_normalised
    np.testing.assert_allclose(np.asarray(quats_to_rotmats(normalize_quats(jnp.asarray(quats, jnp.float32)))),
                               q.T @ np.asarray(quats_to_rotmats(normalize_quats(jnp.asarray(model.quats)))),
                               atol=1e-5)
    K = jnp.array([[40.0, 0, 20], [0, 40, 15], [0, 0, 1]])
    norm_view = np.eye(4)  # a camera at the normalised origin looking down +z
    colmap_view = np.eye(4)
    colmap_view[:3, :3] = q  # its COLMAP-frame pose: world.viewmats(colmap_view) = norm_view
    colmap_view[:3, 3] = -q @ np.asarray(world.center)
    np.testing.assert_allclose(world.viewmats(colmap_view[None])[0], norm_view, atol=1e-12)
    colmap_model = SplatModel(means=means.astype(np.float32), quats=quats.astype(np.float32),
                              log_scales=log_scales.astype(np.float32), opacity_logits=model.opacity_logits,
                              sh=sh.astype(np.float32))
    a = render_splats(model, Camera(K, jnp.asarray(norm_view, jnp.float32), 40, 30), background=(0, 0, 0)).image
    b = render_splats(colmap_model, Camera(K, jnp.asarray(colmap_view, jnp.float32), 40, 30),
                      background=(0, 0, 0)).image
    assert float(jnp.max(a)) > 0.05
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=5e-4)
