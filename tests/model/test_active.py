"""Active-Gaussian compaction (model/active.py): the index maps, the gather's hand-written VJP, and a
training step over the compacted set against the same loss over every decoded Gaussian."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax import losses
from cusgs_jax.config import Config
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.model.active import gather_active, scatter_back, select_active
from cusgs_jax.model.decode import decode_inputs, view_inputs, visible_slots
from cusgs_jax.splat import rasterize
from cusgs_jax.testing.scenes import sfm_points
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import _view_pass
from cusgs_jax.types import Camera


@pytest.mark.parametrize("capacity", [1, 7, 40, 64])
def test_select_active_lists_the_active_ones_in_order_and_counts_what_did_not_fit(capacity):
    rng = np.random.default_rng(capacity)
    active = rng.uniform(size=50) < 0.3
    chosen = select_active(jnp.asarray(active), capacity)
    want = np.flatnonzero(active)
    kept = want[:capacity]
    assert int(chosen.count) == len(want) and int(chosen.overflow) == max(len(want) - capacity, 0)
    np.testing.assert_array_equal(np.asarray(chosen.index)[:len(kept)], kept)
    np.testing.assert_array_equal(np.asarray(chosen.valid), np.arange(capacity) < len(kept))
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(chosen.kept)), kept)
    # position inverts index on the kept ones
    np.testing.assert_array_equal(np.asarray(chosen.position)[kept], np.arange(len(kept)))


def test_gather_and_its_vjp_equal_a_plain_masked_gather_and_scatter_back_inverts_it():
    rng = np.random.default_rng(0)
    active = jnp.asarray(rng.uniform(size=40) < 0.4)
    x = jnp.asarray(rng.normal(size=(40, 3)), jnp.float32)
    chosen = select_active(active, 24)

    def plain(x):  # what autodiff of an ordinary gather gives (a scatter-add on the way back)
        return jnp.where(chosen.valid[:, None], x[chosen.index], 0.0)

    out, vjp = jax.vjp(lambda x: gather_active(x, chosen), x)
    want, want_vjp = jax.vjp(plain, x)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(want))
    for seed in range(3):  # random cotangents, padding rows included
        cot = jnp.asarray(np.random.default_rng(seed + 1).normal(size=out.shape), jnp.float32)
        np.testing.assert_array_equal(np.asarray(vjp(cot)[0]), np.asarray(want_vjp(cot)[0]))
    back = scatter_back(out, chosen)
    np.testing.assert_array_equal(np.asarray(back), np.where(np.asarray(active)[:, None], np.asarray(x), 0.0))
    # and under jit and grad (a pytree of index arrays passes through the custom VJP)
    g = jax.jit(jax.grad(lambda x: jnp.sum(gather_active(x, chosen) ** 2)))(x)
    np.testing.assert_allclose(np.asarray(g), 2 * np.asarray(back), rtol=1e-6)


W, H = 40, 30
K = jnp.array([[36.0, 0, 20], [0, 36, 15], [0, 0, 1]])


def _mostly_masked_state():
    """A small model whose opacity head switches off most Gaussians (bias −0.2 on its last layer: ~4 % active)."""
    cfg = Config().replace(train=dict(iterations=50),
                           model=dict(voxel_size=0.25, n_offsets=6, latent_dim=8, hidden=16, appearance_dim=8))
    state, _ = init_train_state(cfg, sfm_points(), 2, 2.0, make_strategies(cfg))
    key = jax.random.PRNGKey(5)
    params = state.anchors.params
    params = dataclasses.replace(params, latent=jax.random.normal(key, params.latent.shape),
                                 offsets=0.3 * jax.random.normal(jax.random.fold_in(key, 1), params.offsets.shape))
    nets = jax.tree_util.tree_map(lambda x: x, state.nets)
    opacity = dict(nets["decoder"]["opacity"])
    last = max(k for k in opacity if k.startswith("b"))
    opacity[last] = opacity[last] - 0.2
    nets["decoder"] = dict(nets["decoder"], opacity=opacity)
    state = state.replace(anchors=state.anchors.replace(params=params), nets=nets)
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = [0.02, -0.03, 0.1]
    image = np.random.default_rng(0).uniform(0, 1, (H, W, 3)).astype(np.float32)
    batch = dict(image=jnp.asarray(image), camera=Camera(K, jnp.asarray(view), W, H), index=jnp.int32(1))
    return cfg, state, batch


@pytest.mark.slow
def test_the_compacted_step_has_the_loss_and_gradients_of_rasterising_every_decoded_gaussian():
    cfg, state, batch = _mostly_masked_state()
    camera, anchors = batch["camera"], state.anchors
    caps = Capacities(visible_fraction=1.0, active_fraction=0.25, pairs_per_active=20.0)
    loss, grads, parts = jax.jit(_view_pass(cfg, caps, anchors.capacity))(state.trainable, anchors, batch,
                                                                         jax.random.PRNGKey(0), state)
    decoded_count = parts["gaussians"].means.shape[0]
    active = int(parts["work"]["active_gaussians"])
    assert int(parts["work"]["dropped_gaussians"]) == 0 and int(parts["work"]["dropped_pairs"]) == 0
    assert 0 < active < 0.25 * decoded_count  # the mask removed most of them, and G_act < S·N

    view = visible_slots(anchors, camera, num_slots=anchors.capacity, margin=cfg.model.frustum_margin)

    @jax.jit
    def reference(local, delta):  # no compaction: every decoded Gaussian is rasterised (masked ones culled)
        centers, decoded = anchors.centers[view.slots], anchors.alive[view.slots] & view.valid
        inputs = view_inputs(local, local["anchor"], centers, decoded, camera, batch["index"], cfg.model)
        g = decode_inputs(local["decoder"], inputs, cfg.model.decoder())
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, camera.world_to_camera, camera.K, W, H,
                        tile_size=cfg.splat.tile_size, max_pairs=64 * decoded_count, means2d_delta=delta,
                        background=jnp.asarray(cfg.splat.background_color, jnp.float32))
        return losses.image_loss(out.image, batch["image"], g.scales, g.active, l1_weight=cfg.loss.l1_weight,
                                 ssim_weight=cfg.loss.ssim_weight, volume_weight=cfg.loss.volume_weight)[0]

    local = dict(state.trainable, anchor=jax.tree_util.tree_map(lambda x: x[view.slots], state.trainable["anchor"]))
    want, (want_grads, want_grad2d) = jax.value_and_grad(reference, argnums=(0, 1))(
        local, jnp.zeros((decoded_count, 2), jnp.float32))
    np.testing.assert_allclose(float(loss), float(want), rtol=1e-6)
    flat, want_flat = jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(want_grads)
    assert len(flat) == len(want_flat)
    for got, exp in zip(flat, want_flat):
        scale = float(np.max(np.abs(np.asarray(exp)))) or 1.0
        np.testing.assert_allclose(np.asarray(got), np.asarray(exp), atol=2e-5 * scale, rtol=1e-4)
    # the screen-space gradient the densification statistics read, back in decoded order
    np.testing.assert_allclose(np.asarray(parts["grad2d"]), np.asarray(want_grad2d),
                               atol=2e-5 * float(np.max(np.abs(np.asarray(want_grad2d)))))
