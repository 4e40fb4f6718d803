"""Resizing a real training state: capacity growth and row restarts across anchors, Adam moments, statistics.

The trap these tests set: every network width (decoder hidden size, appearance
embedding rows and size, query-head width) *equals* the anchor capacity, so an
implementation that finds per-anchor arrays by their shape would resize network
weights and their Adam moments too.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, FeatureConfig, FeatureModelConfig, ModelConfig
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import make_strategies
from cusgs_jax.model.anchors import voxelize
from cusgs_jax.training.state import init_train_state

VOXEL = 0.5


def _points():
    return np.random.default_rng(0).uniform(-1, 1, (80, 3))


@functools.lru_cache(maxsize=None)
def _state(granularity):
    """A TrainState with non-zero Adam moments and statistics; every network width = the capacity.

    Cached: states are immutable pytrees and the operations under test are pure.
    """
    capacity = int(np.ceil(2.0 * len(voxelize(_points(), VOXEL))))
    cfg = Config(model=ModelConfig(voxel_size=VOXEL, n_offsets=3, latent_dim=5, hidden=capacity,
                                   appearance_dim=capacity, capacity_factor=2.0, query_granularity=granularity),
                 features=FeatureConfig(models=(FeatureModelConfig("alpha", query_dim=4),), hidden=capacity))
    banks = {"alpha": jnp.asarray(np.random.default_rng(1).normal(size=(capacity, 6)), jnp.float32)}
    state, tx = init_train_state(cfg, _points(), capacity, 1.0, make_strategies(cfg), banks)
    assert state.anchors.capacity == capacity
    rng = np.random.default_rng(2)
    fill = lambda x: jnp.asarray(rng.uniform(0.5, 2.0, np.shape(x)), jnp.asarray(x).dtype)  # noqa: E731
    # every moment (and step count) non-zero, so a zeroed or moved row is seen
    opt_state = jax.tree_util.tree_map(fill, state.opt_state)
    densify = jax.tree_util.tree_map(fill, state.densify)
    return state.replace(opt_state=opt_state, densify=densify), tx


def _is_anchor_moment(path) -> bool:
    """Adam moments mirror the trainable tree {"anchor": AnchorParams, **nets}."""
    return "['anchor']" in jax.tree_util.keystr(path)


def _assert_same(x, y, what):
    x, y = np.asarray(x), np.asarray(y)
    assert x.shape == y.shape, what
    np.testing.assert_array_equal(x, y, err_msg=what)


def _assert_grown(before, after, old, new, what):
    before, after = np.asarray(before), np.asarray(after)
    assert after.shape == (new,) + before.shape[1:], what
    np.testing.assert_array_equal(after[:old], before, err_msg=what)
    assert not np.any(after[old:]), what  # new rows zero (alive False)


@pytest.mark.parametrize("granularity", ["per_anchor", "per_gaussian"])
def test_grow_capacity_resizes_per_anchor_leaves_only(granularity):
    state, tx = _state(granularity)
    old = state.anchors.capacity
    new = old + 37

    # the trap is real: network weights and their moments have the capacity as an axis
    net_shapes = [x.shape for x in jax.tree_util.tree_leaves(state.nets)]
    assert any(s and s[0] == old for s in net_shapes) and sum(old in s for s in net_shapes) >= 6
    net_moments = [x.shape for p, x in jax.tree_util.tree_leaves_with_path(state.opt_state)
                   if not _is_anchor_moment(p)]
    assert any(s and s[0] == old for s in net_moments)

    grown = ops.grow_capacity(state, tx, new)

    # no network weight changes, in shape or value
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.nets), jax.tree_util.tree_leaves(grown.nets)):
        _assert_same(x, y, "nets" + jax.tree_util.keystr(path))
    assert jax.tree_util.tree_structure(grown.nets) == jax.tree_util.tree_structure(state.nets)

    # Adam: the anchors' moments grow with zero new rows, the networks' moments and counts are untouched
    assert jax.tree_util.tree_structure(grown.opt_state) == jax.tree_util.tree_structure(state.opt_state)
    grown_anchor_moments = 0
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.opt_state),
                            jax.tree_util.tree_leaves(grown.opt_state)):
        what = "opt_state" + jax.tree_util.keystr(path)
        if _is_anchor_moment(path):
            _assert_grown(x, y, old, new, what)
            grown_anchor_moments += 1
        else:
            _assert_same(x, y, what)
    # mu and nu of offsets, log_scaling, latent (+ the per-Gaussian query table)
    assert grown_anchor_moments == 2 * (4 if granularity == "per_gaussian" else 3)

    # every per-anchor array of the anchors and of every strategy's statistics grows
    assert grown.anchors.capacity == new
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.anchors),
                            jax.tree_util.tree_leaves(grown.anchors)):
        _assert_grown(x, y, old, new, "anchors" + jax.tree_util.keystr(path))
    assert set(grown.densify) == {"scaffold", "feature_prune"}
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.densify),
                            jax.tree_util.tree_leaves(grown.densify)):
        _assert_grown(x, y, old, new, "densify" + jax.tree_util.keystr(path))
    _assert_same(state.step, grown.step, "step")
    _assert_same(state.skipped, grown.skipped, "skipped")

    # the optimiser still accepts the grown tree (its moments mirror the grown parameters)
    updates, new_opt = jax.eval_shape(tx.update, grown.trainable, grown.opt_state, grown.trainable)
    for u, p in zip(jax.tree_util.tree_leaves(updates), jax.tree_util.tree_leaves(grown.trainable)):
        assert u.shape == p.shape
    assert [x.shape for x in jax.tree_util.tree_leaves(new_opt)] == [
        x.shape for x in jax.tree_util.tree_leaves(grown.opt_state)]


def test_restart_rows_zeroes_only_the_given_rows():
    state, tx = _state("per_gaussian")
    capacity = state.anchors.capacity
    rows = np.zeros(capacity, bool)
    rows[[0, 5, capacity - 1]] = True
    after = ops.restart_rows(state, tx, jnp.asarray(rows))

    touched = 0
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.opt_state),
                            jax.tree_util.tree_leaves(after.opt_state)):
        what = "opt_state" + jax.tree_util.keystr(path)
        x, y = np.asarray(x), np.asarray(y)
        if _is_anchor_moment(path):
            assert np.all(x[rows] != 0) and not np.any(y[rows]), what
            np.testing.assert_array_equal(y[~rows], x[~rows], err_msg=what)
            touched += 1
        else:  # network moments (some capacity-wide) and step counts are left alone
            _assert_same(x, y, what)
    assert touched == 8  # mu and nu of offsets, log_scaling, latent, query_table
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.densify),
                            jax.tree_util.tree_leaves(after.densify)):
        what = "densify" + jax.tree_util.keystr(path)
        x, y = np.asarray(x), np.asarray(y)
        assert not np.any(y[rows]), what
        np.testing.assert_array_equal(y[~rows], x[~rows], err_msg=what)
    # the anchors themselves and the networks are not restart_rows' business
    for x, y in zip(jax.tree_util.tree_leaves((state.anchors, state.nets)),
                    jax.tree_util.tree_leaves((after.anchors, after.nets))):
        _assert_same(x, y, "anchors/nets")
