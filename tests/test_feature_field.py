"""Feature field: query heads, the feature loss, and paying only for what a scene uses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.feature_field import (FeatureConfig, FeatureModelConfig, decode_queries, feature_loss,
                                     init_query_heads, refill_query_table)
from cusgs_jax.grow_prune import GrowConfig
from cusgs_jax.train import ModelConfig, TrainConfig, init_train_state, make_train_step

W, H = 32, 24
K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
# distinctive sizes so the jaxpr test can look for them: Q = 17 + 20 = 37 query channels, S = 23 entries
MODELS = (FeatureModelConfig("alpha", query_dim=17), FeatureModelConfig("beta", query_dim=20))


def _cfg(features=True, granularity="per_anchor"):
    feats = FeatureConfig(models=MODELS if features else (), granularity=granularity, sample_pixels=100)
    return TrainConfig(iterations=50, features=feats,
                       model=ModelConfig(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
                       grow=GrowConfig(stats_start=0, start=1000, stop=1000))


def _points():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (400, 3))
    pts[:, 2] += 3.0
    return pts


def _banks():
    rng = np.random.default_rng(1)
    return {"alpha": jnp.asarray(rng.normal(size=(23, 6)), jnp.float32),
            "beta": jnp.asarray(rng.normal(size=(23, 9)), jnp.float32)}


def _batch(features=True, seed=0):
    rng = np.random.default_rng(seed)
    batch = dict(image=jnp.asarray(rng.uniform(0, 1, (H, W, 3)), jnp.float32), viewmat=jnp.eye(4), K=K,
                 index=jnp.int32(0))
    if features:
        banks = _banks()
        alpha = np.asarray(banks["alpha"])[rng.integers(0, 23, (H, W))]
        alpha[:3] = 0.0  # "no target" rows
        beta = np.asarray(banks["beta"])[rng.integers(0, 23, (H // 2, W // 2))]  # lower resolution
        batch.update(features={"alpha": jnp.asarray(alpha), "beta": jnp.asarray(beta)}, banks=banks)
    return batch


def test_query_heads_shapes_and_granularity():
    cfg = FeatureConfig(models=MODELS)
    key = jax.random.PRNGKey(0)
    latent, direction = jnp.ones((5, 8)), jnp.ones((5, 3)) / np.sqrt(3)
    offsets = jnp.asarray(np.random.default_rng(0).normal(size=(5, 4, 3)), jnp.float32)
    params = init_query_heads(key, cfg, 8, 0, 4, capacity=10)
    q = decode_queries(params, latent, direction, None, offsets, jnp.arange(5), cfg)
    assert q.shape == (20, 37)
    # per-Gaussian queries differ through the offsets (hierarchy), equal offsets → equal queries
    q2 = decode_queries(params, latent, direction, None, jnp.zeros_like(offsets), jnp.arange(5), cfg)
    assert not np.allclose(q[:4], q[1:5]) and np.allclose(q2[0], q2[1])
    table_cfg = FeatureConfig(models=MODELS, granularity="per_gaussian")
    table = init_query_heads(key, table_cfg, 8, 0, 4, capacity=10)
    assert table["table"].shape == (10, 4, 37)
    qt = decode_queries(table, latent, direction, None, offsets, jnp.array([9, 0, 1, 2, 3]), table_cfg)
    np.testing.assert_array_equal(qt[:4], table["table"][9])


def test_feature_loss_masks_invalid_pixels():
    pred = jnp.array([[1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    target = jnp.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    loss, terms = feature_loss(pred, target, jnp.array([True, True, False]))
    np.testing.assert_allclose(terms["l2"], (0.0 + 1.0) / 2)
    np.testing.assert_allclose(terms["cos"], (0.0 + 1.0) / 2)
    np.testing.assert_allclose(loss, 1.0)


def test_scene_without_features_traces_no_feature_work():
    for enabled in (False, True):
        cfg = _cfg(features=enabled)
        state, tx = init_train_state(cfg, _points(), 1, 2.0, banks=_banks() if enabled else None)
        assert ("queries" in state.params) == enabled and ("memory" in state.params) == enabled
        step = make_train_step(cfg, tx, W, H)
        text = str(jax.make_jaxpr(step)(state, _batch(enabled)))
        has_query_channels = ",40]" in text  # 3 RGB + 37 query channels composited together
        has_bank = "[23," in text  # memory entries enter the attention
        assert has_query_channels == enabled and has_bank == enabled, enabled


def test_feature_training_step_runs_and_learns():
    cfg = _cfg()
    state, tx = init_train_state(cfg, _points(), 1, 2.0, banks=_banks())
    step = make_train_step(cfg, tx, W, H)
    batch = _batch()
    first = None
    for _ in range(15):
        state, metrics = step(state, batch)
        first = float(metrics["loss_feature"]) if first is None else first
    assert bool(metrics["finite"]) and np.isfinite(float(metrics["loss_feature"]))
    assert float(metrics["loss_feature"]) < first
    assert step._cache_size() == 1


def test_per_gaussian_query_ablation_trains():
    cfg = _cfg(granularity="per_gaussian")
    state, tx = init_train_state(cfg, _points(), 1, 2.0, banks=_banks())
    assert state.params["queries"]["table"].shape[:2] == state.params["anchor"].offsets.shape[:2]
    step = make_train_step(cfg, tx, W, H)
    before = np.asarray(state.params["queries"]["table"]).copy()
    for _ in range(3):
        state, metrics = step(state, _batch())
    assert bool(metrics["finite"])
    assert not np.array_equal(before, np.asarray(state.params["queries"]["table"]))


def test_m3_query_split_when_dims_are_not_given():
    cfg = FeatureConfig(models=tuple(FeatureModelConfig(n) for n in ("clip", "siglip", "dinov2", "seem",
                                                                     "llama3", "llamav")))
    assert cfg.query_dim == 160 and [m.query_dim for m in cfg.models] == [16, 32, 32, 16, 32, 32]


def test_refilled_slots_get_fresh_queries_and_moments():
    """A slot refilled by growing must not inherit the per-Gaussian queries (or their Adam
    moments) of the anchor that lived there before; other slots are untouched."""
    from cusgs_jax.optim import reset_rows

    cfg = _cfg(granularity="per_gaussian")
    state, tx = init_train_state(cfg, _points(), 2, 2.0, _banks())
    step = make_train_step(cfg, tx, W, H)
    for i in range(2):
        state, _ = step(state, _batch(seed=i))
    capacity = state.anchors.capacity
    rows = np.zeros(capacity, bool)
    rows[[1, 4, capacity - 1]] = True
    table = state.params["queries"]["table"]
    new = np.asarray(refill_query_table(table, jnp.asarray(rows), jax.random.PRNGKey(3)))
    np.testing.assert_array_equal(new[~rows], np.asarray(table)[~rows])
    assert np.all(new[rows] != np.asarray(table)[rows])
    assert 0.02 < np.std(new[rows]) < 0.5  # drawn like the initial table (0.1 · N(0, 1))

    before = state.opt_state
    after = reset_rows(before, jnp.asarray(rows), capacity, group="table")
    touched = 0
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(before), jax.tree_util.tree_leaves(after)):
        x, y = np.asarray(x), np.asarray(y)
        if "table" in jax.tree_util.keystr(path) and x.ndim and x.shape[0] == capacity:
            assert np.any(x[rows] != 0) and np.all(y[rows] == 0)
            np.testing.assert_array_equal(y[~rows], x[~rows])
            touched += 1
        else:  # anchor moments and everything else are left alone
            np.testing.assert_array_equal(y, x)
    assert touched == 2  # Adam's mu and nu of the table
