"""The jitted train step: compiles once, deterministic, skips non-finite updates."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.grow_prune import GrowConfig, adjust_anchors
from cusgs_jax.prune import prune_due
from cusgs_jax.train import (ModelConfig, TrainConfig, compact_for_render, init_train_state, make_prune_step,
                             make_render_fn, make_train_step, render_config)

W, H = 32, 24
K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])


def _cfg(**grow):
    return TrainConfig(iterations=50, model=ModelConfig(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16,
                                                        appearance_dim=8),
                       grow=GrowConfig(**{**dict(stats_start=0, start=5, stop=50, interval=5), **grow}))


def _points():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (400, 3))
    pts[:, 2] += 3.0
    return pts


def _batch(seed=0, nan=False):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    if nan:
        image[3, 4, 1] = np.nan
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = rng.normal(0, 0.05, 3)
    return dict(image=jnp.asarray(image), viewmat=jnp.asarray(view), K=K, index=jnp.int32(seed % 2))


@pytest.fixture(scope="module")
def setup():
    cfg = _cfg(grad_threshold=0.0, min_opacity=0.2, success_threshold=0.8)
    state, tx = init_train_state(cfg, _points(), 2, 2.0)
    return cfg, tx, make_train_step(cfg, tx, W, H), state


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)


def test_step_compiles_once_across_growing_and_pruning(setup):
    cfg, tx, step, state = setup
    state = _copy(state)
    grown = pruned = 0
    for i in range(20):
        state, metrics = step(state, _batch(i))
        if (i + 1) % cfg.grow.interval == 0:
            anchor, anchors, stats, opt, info = adjust_anchors(
                state.params["anchor"], state.anchors, state.stats, state.opt_state, cfg.grow,
                cfg.model.voxel_size, np.random.default_rng(i))
            assert info["capacity_grew"] is None
            grown += info["grown"]
            pruned += info["pruned"]
            state = dataclasses.replace(state, params=dict(state.params, anchor=anchor), opt_state=opt, anchors=anchors,
                                        stats=stats)
    assert grown > 0 and pruned > 0  # the masks really changed
    assert step._cache_size() == 1
    assert int(state.step) == 20 and bool(metrics["finite"])


def test_same_seed_same_numbers(setup):
    cfg, tx, step, state0 = setup
    finals = []
    for _ in range(2):
        state = _copy(state0)
        for i in range(3):
            state, metrics = step(state, _batch(i))
        finals.append((jax.device_get(state.params), float(metrics["loss"])))
    assert finals[0][1] == finals[1][1]
    for a, b in zip(jax.tree_util.tree_leaves(finals[0][0]), jax.tree_util.tree_leaves(finals[1][0])):
        np.testing.assert_array_equal(a, b)


def test_non_finite_update_is_skipped_and_counted(setup):
    cfg, tx, step, state0 = setup
    state, _ = step(_copy(state0), _batch(0))
    before = jax.device_get((state.params, state.opt_state))
    state, metrics = step(state, _batch(1, nan=True))
    assert not bool(metrics["finite"]) and int(state.skipped) == 1
    after = jax.device_get((state.params, state.opt_state))
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a, b)
    state, metrics = step(state, _batch(2))
    assert bool(metrics["finite"]) and int(state.skipped) == 1


def test_dead_anchors_do_not_move(setup):
    cfg, tx, step, state0 = setup
    state = _copy(state0)
    alive = np.asarray(state.anchors.alive).copy()
    alive[:5] = False
    state = dataclasses.replace(state, anchors=type(state.anchors)(state.anchors.centers, jnp.asarray(alive)))
    before = jax.device_get(state.params["anchor"])
    for i in range(2):
        state, _ = step(state, _batch(i))
    after = jax.device_get(state.params["anchor"])
    moved = False
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a[:5], b[:5])
        moved |= not np.array_equal(a[alive], b[alive])
    assert moved


# ---------------------------------------------------------------- feature-aware pruning in training

def _prune_cfg(**prune):
    from cusgs_jax.prune import PruneConfig

    base = {"strategy": "feature_aware", "ratio": 0.1, "interval": 3, "start": 3, "stop": 50, "min_visits": 0}
    return dataclasses.replace(_cfg(), prune=PruneConfig(**{**base, **prune}))


@pytest.fixture(scope="module")
def prune_setup():
    cfg = _prune_cfg()
    state, tx = init_train_state(cfg, _points(), 2, 2.0)
    return cfg, make_train_step(cfg, tx, W, H), make_prune_step(cfg), state


def test_prune_statistics_equal_a_direct_float64_computation(prune_setup):
    """One step's PruneStats against a direct computation: autodiff of the same loss for ∇z, the
    float64 reference rasteriser for Σ opacity·T, and testing.prune_reference for the score."""
    from cusgs_jax import losses
    from cusgs_jax.prune import anchor_scores
    from cusgs_jax.splat.reference import rasterize_reference
    from cusgs_jax.testing.prune_reference import significance_reference
    from cusgs_jax.train import decode_view, render_gaussians

    cfg, step, _, state0 = prune_setup
    batch = _batch(3)
    params, anchors = jax.device_get(state0.params), state0.anchors

    def loss_of(p):
        g, slots, valid, _ = decode_view(p, anchors, batch["viewmat"], batch["K"], W, H, batch["index"], cfg)
        out = render_gaussians(g, batch["viewmat"], batch["K"], W, H, cfg)
        loss, _ = losses.image_loss(out.image, batch["image"], g.scales, g.active, l1_weight=cfg.loss.l1_weight,
                                    ssim_weight=cfg.loss.ssim_weight, volume_weight=cfg.loss.volume_weight)
        return loss, (g, slots, valid)

    grads, (g, slots, valid) = jax.grad(loss_of, has_aux=True)(params)
    reference = rasterize_reference(np.asarray(g.means), np.asarray(g.quats), np.asarray(g.scales),
                                    np.asarray(g.opacities), np.asarray(g.colors), np.asarray(batch["viewmat"]),
                                    np.asarray(batch["K"]), W, H)
    view = {"slots": np.asarray(slots), "valid": np.asarray(valid),
            "latent_grad": np.asarray(grads["anchor"].latent)[np.asarray(slots)],
            "significance": reference["significance"], "scales": np.asarray(g.scales),
            "active": np.asarray(g.active)}
    state, _ = step(_copy(state0), batch)
    latent = np.asarray(state.params["anchor"].latent)
    alive = np.asarray(state.anchors.alive)
    expected = significance_reference(latent, alive, [view], cfg.prune)
    got = np.asarray(anchor_scores(state.params["anchor"].latent, state.prune, state.anchors.alive, cfg.prune))
    assert np.sum(np.asarray(state.prune.contrib) > 0) > 10  # the view really touched many anchors
    np.testing.assert_array_equal(np.isinf(got), np.isinf(expected))
    np.testing.assert_allclose(got[alive], expected[alive], rtol=2e-4, atol=1e-5)
    seen = np.zeros(len(alive), bool)
    seen[np.asarray(slots)[np.asarray(valid)]] = True
    np.testing.assert_array_equal(np.asarray(state.prune.grad_count), seen.astype(np.float32))


def test_prune_pass_honours_ratio_and_pruned_anchors_are_inert(prune_setup):
    cfg, step, prune, state0 = prune_setup
    state = _copy(state0)
    for i in range(3):
        state, _ = step(state, _batch(i))
    alive_before = np.asarray(state.anchors.alive)
    state, info = prune(state)
    alive_after = np.asarray(state.anchors.alive)
    removed = alive_before & ~alive_after
    assert int(info["pruned"]) == removed.sum() == int(0.1 * alive_before.sum()) > 0
    assert not np.any(alive_after & ~alive_before)
    assert float(jnp.sum(state.prune.contrib)) == 0.0  # statistics restart after a pass

    # pruned anchors contribute nothing: the render equals the render of the model without them ...
    batch = _batch(5)
    render = make_render_fn(cfg, W, H)
    image, _ = render(state.params, state.anchors, batch["viewmat"], batch["K"], batch["index"])
    compact_params, compact_anchors = compact_for_render(state.params, state.anchors)
    assert compact_anchors.capacity < state.anchors.capacity
    compact_image, _ = make_render_fn(render_config(cfg), W, H)(
        compact_params, compact_anchors, batch["viewmat"], batch["K"], batch["index"])
    np.testing.assert_allclose(np.asarray(image), np.asarray(compact_image), atol=1e-6)

    # ... their parameters get exactly zero gradient and do not move in later steps
    def image_sum(anchor_params):
        params = dict(state.params, anchor=anchor_params)
        return jnp.sum(render(params, state.anchors, batch["viewmat"], batch["K"], batch["index"])[0])

    grad = jax.grad(image_sum)(state.params["anchor"])
    for leaf in jax.tree_util.tree_leaves(grad):
        assert np.all(np.asarray(leaf)[removed] == 0)
    before = jax.device_get(state.params["anchor"])
    for i in range(3):
        state, _ = step(state, _batch(10 + i))
    after = jax.device_get(state.params["anchor"])
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a[removed], b[removed])
    assert step._cache_size() == 1 and prune._cache_size() == 1  # masks, not new shapes


def test_prune_ratio_counts_exactly_and_repeated_passes_do_not_recompile(prune_setup):
    cfg, step, prune, state0 = prune_setup
    state = _copy(state0)
    counts = [int(np.sum(state.anchors.alive))]
    for i in range(12):
        state, _ = step(state, _batch(i))
        if prune_due(int(state.step), cfg.prune):
            state, info = prune(state)
            counts.append(int(info["alive"]))
    assert len(counts) == 5  # passes at steps 3, 6, 9, 12
    for before, after in zip(counts, counts[1:]):
        assert after == before - before // 10
    assert step._cache_size() == 1 and prune._cache_size() == 1


def test_strategy_none_keeps_every_anchor_and_collects_nothing():
    cfg = _prune_cfg(strategy="none")
    state, tx = init_train_state(cfg, _points(), 2, 2.0)
    step, prune = make_train_step(cfg, tx, W, H), make_prune_step(cfg)
    alive = np.asarray(state.anchors.alive).copy()
    for i in range(3):
        state, _ = step(state, _batch(i))
    assert all(float(jnp.sum(x)) == 0.0 for x in jax.tree_util.tree_leaves(state.prune))
    state, info = prune(state)
    assert int(info["pruned"]) == 0
    np.testing.assert_array_equal(np.asarray(state.anchors.alive), alive)
