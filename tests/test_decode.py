"""Anchor decoding: shapes, formulas, culling and dead anchors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.decode import DecoderConfig, apply_mlp, decode_gaussians, frustum_mask, init_decoder, init_mlp
from cusgs_jax.scaffold import AnchorParams, Anchors


def _setup(num=6, n=4, f=8, e=5):
    cfg = DecoderConfig(n_offsets=n, latent_dim=f, hidden=16, appearance_dim=e)
    rng = np.random.default_rng(0)
    anchor = AnchorParams(offsets=jnp.asarray(rng.normal(size=(num, n, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (num, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(num, f)), jnp.float32))
    anchors = Anchors(jnp.asarray(rng.uniform(-1, 1, (num, 3)), jnp.float32), jnp.ones(num, bool))
    return cfg, init_decoder(jax.random.PRNGKey(0), cfg), anchor, anchors


def test_mlp_matches_numpy():
    p = init_mlp(jax.random.PRNGKey(1), (5, 7, 3))
    x = np.random.default_rng(0).normal(size=(4, 5)).astype(np.float32)
    h = np.maximum(x @ np.asarray(p["w0"]) + np.asarray(p["b0"]), 0)
    np.testing.assert_allclose(apply_mlp(p, jnp.asarray(x)), h @ np.asarray(p["w1"]) + np.asarray(p["b1"]), rtol=1e-5)


def test_decode_formulas_and_shapes():
    cfg, params, anchor, anchors = _setup()
    cam = jnp.array([0.0, 0.0, -3.0])
    app = jnp.ones(5)
    g = decode_gaussians(params, anchor, anchors, cam, app, jnp.ones(6, bool), cfg)
    assert g.means.shape == (24, 3) and g.quats.shape == (24, 4) and g.colors.shape == (24, 3)
    scaling = np.exp(np.asarray(anchor.log_scaling))
    expect = np.asarray(anchors.centers)[:, None] + np.asarray(anchor.offsets) * scaling[:, None, :3]
    np.testing.assert_allclose(g.means, expect.reshape(-1, 3), rtol=1e-6)
    # scales bounded by the anchor's base scale (sigmoid ≤ 1)
    assert np.all(np.asarray(g.scales).reshape(6, 4, 3) <= scaling[:, None, 3:] + 1e-7)
    opac = np.asarray(g.opacities)
    assert np.all((opac >= 0) & (opac <= 1)) and np.array_equal(opac > 0, np.asarray(g.active))


def test_dead_and_culled_anchors_are_switched_off():
    cfg, params, anchor, anchors = _setup()
    alive = jnp.array([True, False, True, True, True, True])
    visible = jnp.array([True, True, True, False, True, True])
    g = decode_gaussians(params, anchor, Anchors(anchors.centers, alive), jnp.zeros(3), jnp.zeros(5),
                         visible, cfg)
    opac = np.asarray(g.opacities).reshape(6, 4)
    assert np.all(opac[1] == 0) and np.all(opac[3] == 0)


def test_no_appearance_branch_when_disabled():
    cfg = DecoderConfig(n_offsets=3, latent_dim=4, hidden=8, appearance_dim=0)
    params = init_decoder(jax.random.PRNGKey(0), cfg)
    assert params["color"]["w0"].shape[0] == 4 + 3


def test_frustum_mask():
    centers = jnp.array([[0.0, 0, 2], [0, 0, -2], [100, 0, 2], [0.5, 0.3, 2]])
    K = jnp.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48), [True, False, False, True])
