"""Feature queries: the hierarchical per-anchor heads, the per-Gaussian table ablation, refilled slots."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import FeatureConfig
from cusgs_jax.densify import ops
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.model.anchors import AnchorParams, init_anchors, place_anchors, take_rows
from cusgs_jax.model.decode import ViewInputs
from cusgs_jax.model.queries import decode_queries, init_query_heads
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step


def _inputs(rows, direction, appearance=None) -> ViewInputs:
    """A view's inputs with the given directions [S, 3] (the centres are not read by the query heads)."""
    num = direction.shape[0]
    return ViewInputs(rows, jnp.zeros((num, 3)), jnp.ones(num, bool), direction, appearance)


def test_query_heads_shapes_and_granularity(feature_scene):
    cfg = FeatureConfig(models=feature_scene.models)
    key = jax.random.PRNGKey(0)
    latent, direction = jnp.ones((5, 8)), jnp.ones((5, 3)) / np.sqrt(3)
    offsets = jnp.asarray(np.random.default_rng(0).normal(size=(5, 4, 3)), jnp.float32)
    anchor = AnchorParams(offsets=offsets, log_scaling=jnp.zeros((5, 6)), latent=latent)
    params = init_query_heads(key, cfg, 8, 0)
    q = decode_queries(params, _inputs(anchor, direction))
    assert q.shape == (20, 37)
    # per-Gaussian queries differ through the offsets (hierarchy), equal offsets → equal queries
    flat = AnchorParams(offsets=jnp.zeros_like(offsets), log_scaling=anchor.log_scaling, latent=latent)
    q2 = decode_queries(params, _inputs(flat, direction))
    assert not np.allclose(q[:4], q[1:5]) and np.allclose(q2[0], q2[1])
    # per_gaussian: a [A, N, Q] table stored with the anchors, read through the gathered slots
    anchors = init_anchors(feature_scene.points(), 0.25, n_offsets=4, latent_dim=8, query_dim=cfg.query_dim,
                           key=key)
    table = anchors.params.query_table
    assert table.shape == (anchors.capacity, 4, 37) and anchors.capacity > 9
    slots = jnp.array([9, 0, 1, 2, 3])
    qt = decode_queries(None, _inputs(take_rows(anchors.params, slots), direction))
    np.testing.assert_array_equal(qt[:4], table[9])
    np.testing.assert_array_equal(qt.reshape(5, 4, 37), table[slots])


def test_query_heads_against_numpy(feature_scene):
    """q_v = MLP(z, d, e); q_{v,n} = Linear([q_v, Δx_{v,n}]), written out in NumPy."""
    cfg = FeatureConfig(models=feature_scene.models, hidden=12)
    rng = np.random.default_rng(1)
    heads = init_query_heads(jax.random.PRNGKey(2), cfg, 8, 3)
    assert heads["voxel"]["w0"].shape == (8 + 3 + 3, 12) and heads["gaussian"]["w0"].shape == (37 + 3, 37)
    anchor = AnchorParams(offsets=jnp.asarray(rng.normal(size=(5, 4, 3)), jnp.float32),
                          log_scaling=jnp.zeros((5, 6)), latent=jnp.asarray(rng.normal(size=(5, 8)), jnp.float32))
    direction = rng.normal(size=(5, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    appearance = rng.normal(size=3)
    q = decode_queries(heads, _inputs(anchor, jnp.asarray(direction, jnp.float32), jnp.asarray(appearance, jnp.float32)))
    h = {k: {n: np.asarray(v, np.float64) for n, v in p.items()} for k, p in heads.items()}
    x = np.concatenate([np.asarray(anchor.latent), direction, np.tile(appearance, (5, 1))], -1)
    voxel = np.maximum(x @ h["voxel"]["w0"] + h["voxel"]["b0"], 0) @ h["voxel"]["w1"] + h["voxel"]["b1"]
    inputs = np.concatenate([np.repeat(voxel[:, None], 4, 1), np.asarray(anchor.offsets)], -1)
    want = inputs @ h["gaussian"]["w0"] + h["gaussian"]["b0"]
    np.testing.assert_allclose(q, want.reshape(20, 37), rtol=1e-4, atol=1e-5)


@pytest.fixture(scope="module")
def per_gaussian_run(feature_scene):
    """``fresh() -> (state, tx)`` and the train step for the per-Gaussian ablation (2 views), compiled once.

    The step of :func:`make_train_step`, compiled ahead of time (public ``lower().compile()``, donation
    included) at XLA's lowest backend optimisation level: half the compile time on CPU. The executable
    refuses any argument whose structure, shape or dtype differs from the first state's.
    """
    cfg = feature_scene.cfg(granularity="per_gaussian")
    strategies = make_strategies(cfg)

    def fresh():
        return init_train_state(cfg, feature_scene.points(), 2, 2.0, strategies, feature_scene.banks())

    state, tx = fresh()
    step = make_train_step(cfg, tx, strategies)
    compiled = step.lower(state, feature_scene.batch()).compile(
        compiler_options={"xla_backend_optimization_level": 0})
    return fresh, compiled


def test_per_gaussian_query_ablation_trains(feature_scene, per_gaussian_run):
    fresh, step = per_gaussian_run
    state, _ = fresh()
    assert state.anchors.params.query_table.shape[:2] == state.anchors.params.offsets.shape[:2]
    assert "queries" not in state.nets and "memory" in state.nets  # no heads: the table is the query
    before = np.asarray(state.anchors.params.query_table).copy()
    for _ in range(3):
        state, metrics = step(state, feature_scene.batch())
    assert bool(metrics["finite"])
    assert not np.array_equal(before, np.asarray(state.anchors.params.query_table))


def test_refilled_slots_get_fresh_queries_and_moments(feature_scene, per_gaussian_run):
    """A slot refilled by growing must not inherit the per-Gaussian queries (or their Adam
    moments) of the anchor that lived there before; other slots are untouched."""
    fresh, step = per_gaussian_run
    state, tx = fresh()
    for i in range(2):
        state, _ = step(state, feature_scene.batch(seed=i))
    capacity = state.anchors.capacity
    # three slots whose table moments are non-zero (their Gaussians reached a sampled feature pixel), so the
    # restart below has something to clear
    moved = [np.any(np.asarray(x) != 0, axis=tuple(range(1, np.ndim(x))))
             for path, x in jax.tree_util.tree_leaves_with_path(state.opt_state)
             if "query_table" in jax.tree_util.keystr(path)]
    candidates = np.flatnonzero(np.logical_and.reduce(moved))
    assert len(candidates) >= 3
    rows = np.zeros(capacity, bool)
    rows[[candidates[0], candidates[1], candidates[-1]]] = True
    slots = np.flatnonzero(rows)
    table = state.anchors.params.query_table
    anchors = place_anchors(state.anchors, slots, np.zeros((3, 3)), np.zeros((3, 8)), np.zeros(3),
                            jax.random.PRNGKey(3))
    new = np.asarray(anchors.params.query_table)
    np.testing.assert_array_equal(new[~rows], np.asarray(table)[~rows])
    assert np.all(new[rows] != np.asarray(table)[rows])
    assert 0.02 < np.std(new[rows]) < 0.5  # drawn like the initial table (0.1 · N(0, 1))

    before = state.opt_state
    after = ops.restart_rows(state.replace(anchors=anchors), tx, jnp.asarray(rows)).opt_state
    touched = 0
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(before), jax.tree_util.tree_leaves(after)):
        x, y = np.asarray(x), np.asarray(y)
        name = jax.tree_util.keystr(path)
        if "['anchor']" in name:  # every per-anchor moment restarts on the refilled rows only
            assert x.shape[0] == capacity
            assert np.all(y[rows] == 0), name
            np.testing.assert_array_equal(y[~rows], x[~rows])
            if "query_table" in name:
                assert np.any(x[rows] != 0), name
                touched += 1
        else:  # network moments and step counts are left alone
            np.testing.assert_array_equal(y, x)
    assert touched == 2  # Adam's mu and nu of the table
