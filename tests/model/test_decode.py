"""Anchor decoding: shapes, formulas, culling, dead anchors, and the per-view gather of visible slots."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import DecoderConfig, ModelConfig
from cusgs_jax.model.anchors import AnchorParams, AnchorState
from cusgs_jax.model.decode import (decode_gaussians, decode_view, frustum_mask, init_decoder, num_visible_slots,
                                    visible_slots)
from cusgs_jax.nn import apply_mlp, init_mlp
from cusgs_jax.types import Camera


def _setup(num=6, n=4, f=8, e=8):
    # the decoder sizes of tests/model/conftest.py: its random initialisation compiles once per session
    cfg = DecoderConfig(n_offsets=n, latent_dim=f, hidden=16, appearance_dim=e)
    rng = np.random.default_rng(0)
    anchor = AnchorParams(offsets=jnp.asarray(rng.normal(size=(num, n, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (num, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(num, f)), jnp.float32))
    centers = jnp.asarray(rng.uniform(-1, 1, (num, 3)), jnp.float32)
    return cfg, init_decoder(jax.random.PRNGKey(0), cfg), anchor, centers


def test_mlp_matches_numpy():
    p = init_mlp(jax.random.PRNGKey(1), (5, 7, 3))
    x = np.random.default_rng(0).normal(size=(4, 5)).astype(np.float32)
    h = np.maximum(x @ np.asarray(p["w0"]) + np.asarray(p["b0"]), 0)
    np.testing.assert_allclose(apply_mlp(p, jnp.asarray(x)), h @ np.asarray(p["w1"]) + np.asarray(p["b1"]), rtol=1e-5)


def test_decode_formulas_and_shapes():
    cfg, params, anchor, centers = _setup()
    cam = jnp.array([0.0, 0.0, -3.0])
    app = jnp.ones(8)
    g = decode_gaussians(params, anchor, centers, jnp.ones(6, bool), cam, app, cfg)
    assert g.means.shape == (24, 3) and g.quats.shape == (24, 4) and g.colors.shape == (24, 3)
    scaling = np.exp(np.asarray(anchor.log_scaling))
    expect = np.asarray(centers)[:, None] + np.asarray(anchor.offsets) * scaling[:, None, :3]
    np.testing.assert_allclose(g.means, expect.reshape(-1, 3), rtol=1e-6, atol=1e-7)  # |means| ~ 1
    # scales bounded by the anchor's base scale (sigmoid ≤ 1)
    assert np.all(np.asarray(g.scales).reshape(6, 4, 3) <= scaling[:, None, 3:] + 1e-7)
    opac = np.asarray(g.opacities)
    assert np.all((opac >= 0) & (opac <= 1)) and np.array_equal(opac > 0, np.asarray(g.active))
    np.testing.assert_array_equal(g.anchor_index, np.repeat(np.arange(6), 4))


def test_decode_heads_against_numpy():
    """Opacity, covariance and colour heads: the table in model/decode.py, written out in NumPy."""
    cfg, params, anchor, centers = _setup()
    cam, app = np.array([0.2, -0.1, -3.0]), np.linspace(-1, 1, 8)
    g = decode_gaussians(params, anchor, centers, jnp.ones(6, bool), jnp.asarray(cam, jnp.float32),
                         jnp.asarray(app, jnp.float32), cfg)

    def mlp(p, x):
        p = {k: np.asarray(v, np.float64) for k, v in p.items()}
        return np.maximum(x @ p["w0"] + p["b0"], 0) @ p["w1"] + p["b1"]

    direction = np.asarray(centers, np.float64) - cam
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    base = np.concatenate([np.asarray(anchor.latent, np.float64), direction], -1)
    opacity = np.tanh(mlp(params["opacity"], base))
    cov = mlp(params["cov"], base).reshape(6, 4, 7)
    colors = 1 / (1 + np.exp(-mlp(params["color"], np.concatenate([base, np.tile(app, (6, 1))], -1))))
    scaling = np.exp(np.asarray(anchor.log_scaling, np.float64))
    np.testing.assert_allclose(g.opacities, np.maximum(opacity, 0).reshape(-1), atol=1e-5)
    np.testing.assert_allclose(g.quats, cov[..., 3:].reshape(-1, 4), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(g.scales, (scaling[:, None, 3:] / (1 + np.exp(-cov[..., :3]))).reshape(-1, 3),
                               rtol=1e-4)
    np.testing.assert_allclose(g.colors, colors.reshape(-1, 3), rtol=1e-4, atol=1e-6)


def test_dead_and_culled_anchors_are_switched_off():
    cfg, params, anchor, centers = _setup()
    alive = jnp.array([True, False, True, True, True, True])
    visible = jnp.array([True, True, True, False, True, True])
    g = decode_gaussians(params, anchor, centers, alive & visible, jnp.zeros(3), jnp.zeros(8), cfg)
    opac = np.asarray(g.opacities).reshape(6, 4)
    assert np.all(opac[1] == 0) and np.all(opac[3] == 0)
    assert not np.asarray(g.active).reshape(6, 4)[[1, 3]].any()
    everything = np.asarray(decode_gaussians(params, anchor, centers, jnp.ones(6, bool), jnp.zeros(3), jnp.zeros(8),
                                             cfg).opacities).reshape(6, 4)
    np.testing.assert_array_equal(opac[[0, 2, 4, 5]], everything[[0, 2, 4, 5]])  # the others are untouched


def test_no_appearance_branch_when_disabled():
    cfg = DecoderConfig(n_offsets=3, latent_dim=4, hidden=8, appearance_dim=0)
    params = jax.eval_shape(lambda key: init_decoder(key, cfg), jax.random.PRNGKey(0))  # shapes only
    assert params["color"]["w0"].shape[0] == 4 + 3
    assert ModelConfig(latent_dim=4, appearance=False).decoder().appearance_dim == 0


def test_frustum_mask():
    centers = jnp.array([[0.0, 0, 2], [0, 0, -2], [100, 0, 2], [0.5, 0.3, 2]])
    K = jnp.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48), [True, False, False, True])


def _camera():
    """A camera 0.5 behind the origin, looking down +z."""
    viewmat = np.eye(4, dtype=np.float32)
    viewmat[2, 3] = 0.5
    return Camera(jnp.array([[40.0, 0, 32], [0, 40, 24], [0, 0, 1]]), jnp.asarray(viewmat), 64, 48)


def _view_setup(visible_fraction, appearance=True):
    """8 anchor slots: 0, 3 behind the camera, 5 dead, 6 far off-screen; 1, 2, 4, 7 alive and visible.

    The decoder has the sizes of :func:`_setup` (its initialisation compiles once per module).
    """
    rng = np.random.default_rng(3)
    n, f, e = 4, 8, 8
    cfg = ModelConfig(n_offsets=n, latent_dim=f, hidden=16, appearance=appearance, appearance_dim=e,
                      visible_fraction=visible_fraction)
    centers = np.array([[0, 0, -1], [0.1, 0, 2], [-0.2, 0.1, 3], [0, 0, -4],
                        [0.3, -0.2, 2.5], [0, 0, 2], [50, 0, 2], [0, 0.2, 1.5]], np.float32)
    alive = np.array([1, 1, 1, 1, 1, 0, 1, 1], bool)
    params = AnchorParams(offsets=jnp.asarray(rng.normal(size=(8, n, 3)) * 0.1, jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(-2, 0.3, (8, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(8, f)), jnp.float32))
    anchors = AnchorState(jnp.asarray(centers), jnp.asarray(alive), params)
    nets = {"decoder": init_decoder(jax.random.PRNGKey(0), cfg.decoder())}
    if appearance:
        nets["appearance"] = jnp.asarray(rng.normal(size=(4, e)), jnp.float32)
    return cfg, anchors, nets, _camera()


def test_camera_center():
    np.testing.assert_allclose(_camera().center, [0, 0, -0.5])


@jax.jit(static_argnums=3)
def _decode_and_reference(nets, anchors, camera, cfg):
    """decode_view with appearance index 2, and decode_gaussians on the slots it gathered."""
    gaussians, view = decode_view(nets, anchors, camera, jnp.int32(2), cfg,
                                  num_visible_slots(anchors.capacity, cfg.visible_fraction))
    gathered = jax.tree_util.tree_map(lambda x: x[view.slots], anchors.params)
    want = decode_gaussians(nets["decoder"], gathered, anchors.centers[view.slots], view.valid, camera.center,
                            nets["appearance"][2], cfg.decoder())
    return gaussians, view, want


def test_decode_view_gathers_visible_alive_slots():
    visible = [1, 2, 4, 7]
    for fraction, count in ((1.0, 8), (0.6, 5), (0.3, 3)):
        cfg, anchors, nets, camera = _view_setup(fraction)
        assert num_visible_slots(8, fraction) == count
        gaussians, view, want = _decode_and_reference(nets, anchors, camera, cfg)
        assert view.slots.shape == (count,) and gaussians.means.shape == (count * 4, 3)
        if count == 8:  # every slot decoded in slot order, the invisible ones invalid
            np.testing.assert_array_equal(view.slots, np.arange(8))
            np.testing.assert_array_equal(view.valid, np.isin(np.arange(8), visible))
        else:  # the visible alive slots first (in slot order), padding entries repeat slot 0
            kept = visible[:count]
            np.testing.assert_array_equal(view.slots, kept + [0] * (count - len(kept)))
            np.testing.assert_array_equal(view.valid, np.arange(count) < len(kept))
        assert int(view.overflow) == max(len(visible) - count, 0)
        # the same Gaussians as decoding the gathered anchors directly
        for name in ("means", "quats", "scales", "opacities", "colors", "active", "anchor_index"):
            np.testing.assert_allclose(getattr(gaussians, name), getattr(want, name), rtol=1e-6, err_msg=name)
        assert not np.asarray(gaussians.opacities).reshape(count, 4)[~np.asarray(view.valid)].any()


def test_decode_view_appearance_changes_colour_only():
    run = jax.jit(lambda *args: decode_view(*args, 8), static_argnums=4)
    cfg, anchors, nets, camera = _view_setup(1.0)
    a, _ = run(nets, anchors, camera, jnp.int32(0), cfg)
    b, _ = run(nets, anchors, camera, jnp.int32(3), cfg)
    for name in ("means", "quats", "scales", "opacities"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert not np.allclose(a.colors, b.colors)
    # disabled: no embedding is looked up at all (the nets have none)
    plain, anchors, nets_plain, camera = _view_setup(1.0, appearance=False)
    assert "appearance" not in nets_plain and nets_plain["decoder"]["color"]["w0"].shape[0] == 8 + 3
    g, _ = run(nets_plain, anchors, camera, jnp.int32(0), plain)
    assert g.colors.shape == (32, 3) and np.isfinite(np.asarray(g.colors)).all()


def test_visible_slots_jits_once_over_alive_masks(compiles):
    cfg, anchors, _, camera = _view_setup(0.5)
    def slots_of(an, cam):
        return visible_slots(an, cam, num_slots=4, margin=cfg.frustum_margin)

    run = jax.jit(slots_of)
    for kill in ([], [1], [1, 2, 4, 7]):
        alive = np.asarray(anchors.alive).copy()
        alive[kill] = False
        view = run(anchors.replace(alive=jnp.asarray(alive)), camera)
        left = [s for s in (1, 2, 4, 7) if s not in kill]
        assert int(np.sum(view.valid)) == min(len(left), 4)
        np.testing.assert_array_equal(np.asarray(view.slots)[:len(left)], left[:4])
    assert compiles.count("jit(slots_of)") == 1  # one program for every alive mask


def test_frustum_mask_through_a_lens():
    from cusgs_jax.splat.lens import Lens

    K = jnp.asarray([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    # pincushion k1 = 0.5: the point at u = 0.6 lands at u_d = 0.6·(1 + 0.5·0.36) = 0.708 → x = 67.4 px,
    # off a 64-px image with no margin, though its pinhole projection (62 px) is inside
    lens = Lens(jnp.asarray([0.5, 0, 0, 0, 0, 0.0]), jnp.asarray([-0.9, 0.9, -0.9, 0.9]))
    centers = jnp.asarray([[0.6, 0.0, 1.0], [0.2, 0.1, 1.0], [0.95, 0.0, 1.0], [0.0, 0.0, -1.0]])
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48, margin=0.0),
                                  [True, True, False, False])
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48, margin=0.0, lens=lens),
                                  [False, True, False, False])
    wide = Lens(lens.coeffs, jnp.asarray([-2.0, 2.0, -2.0, 2.0]))  # u = 0.95 → u_d = 1.379, 101 px: in a 70 % margin
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48, margin=0.7, lens=wide),
                                  [True, True, True, False])
    np.testing.assert_array_equal(frustum_mask(centers, jnp.eye(4), K, 64, 48, margin=0.7, lens=lens),
                                  [True, True, False, False])  # beyond the trusted box: never visible
