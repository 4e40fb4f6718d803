"""The jitted train step: compiles once, deterministic, skips non-finite updates."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.grow_prune import GrowConfig, adjust_anchors
from cusgs_jax.train import ModelConfig, TrainConfig, TrainState, init_train_state, make_train_step

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
            state = TrainState(dict(state.params, anchor=anchor), opt, anchors, stats, state.step, state.skipped)
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
    state = TrainState(state.params, state.opt_state, type(state.anchors)(state.anchors.centers, jnp.asarray(alive)),
                       state.stats, state.step, state.skipped)
    before = jax.device_get(state.params["anchor"])
    for i in range(2):
        state, _ = step(state, _batch(i))
    after = jax.device_get(state.params["anchor"])
    moved = False
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a[:5], b[:5])
        moved |= not np.array_equal(a[alive], b[alive])
    assert moved
