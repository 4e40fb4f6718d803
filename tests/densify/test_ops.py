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

from cusgs_jax.config import Config, DataConfig, FeatureConfig, FeatureModelConfig, ModelConfig
from cusgs_jax.densify import ops
from cusgs_jax.densify.factory import make_strategies
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


@pytest.mark.slow
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


def test_resize_capacity_moves_the_alive_rows_of_every_per_anchor_array_to_the_front():
    state, tx = _state("per_anchor")
    old = state.anchors.capacity
    alive = np.asarray(state.anchors.alive).copy()
    alive[::3] = False  # a third of the slots dead, scattered
    state = state.replace(anchors=state.anchors.replace(alive=jnp.asarray(alive)))
    keep = np.flatnonzero(alive)
    new = len(keep) + 5
    moved = ops.resize_capacity(state, tx, new)
    assert moved.anchors.capacity == new < old
    for name, before, after in (("anchors", state.anchors, moved.anchors), ("densify", state.densify, moved.densify)):
        for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(before), jax.tree_util.tree_leaves(after)):
            what = name + jax.tree_util.keystr(path)
            np.testing.assert_array_equal(np.asarray(y)[:len(keep)], np.asarray(x)[keep], err_msg=what)
            assert not np.any(np.asarray(y)[len(keep):]), what
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.opt_state),
                            jax.tree_util.tree_leaves(moved.opt_state)):
        if _is_anchor_moment(path):
            np.testing.assert_array_equal(np.asarray(y)[:len(keep)], np.asarray(x)[keep])
        else:
            _assert_same(x, y, "opt_state" + jax.tree_util.keystr(path))
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(state.nets), jax.tree_util.tree_leaves(moved.nets)):
        _assert_same(x, y, "nets" + jax.tree_util.keystr(path))
    with pytest.raises(ValueError, match="cannot keep"):
        ops.resize_capacity(state, tx, len(keep) - 1)


@pytest.mark.slow  # ~20 s end to end (trains, shrinks, steps): in .ci/run's -m slow pass; the shrink itself is tested above
def test_a_step_on_the_shrunk_state_updates_every_alive_anchor_as_before(tmp_path):
    """Dead slots contribute nothing: the step on the compacted capacity gives the alive anchors the
    same loss and the same new parameters (float32 tolerance: the gathers' padding differs)."""
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.data.demo import generate_demo_scene
    from cusgs_jax.training.capacity import Capacities
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.training.step import make_train_step
    from cusgs_jax.types import Camera

    scene_dir = generate_demo_scene(tmp_path / "demo", width=40, height=30, num_views=4, num_points=1500)
    scene, _ = normalize_scene(load_scene(scene_dir, DataConfig(format="colmap", holdout_every=0)))
    cfg = Config().replace(features=dict(models=()), model=dict(n_offsets=3, latent_dim=8, hidden=16))
    cfg = resolve_voxel_size(cfg, scene.points)
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, scene.points, len(scene.images), scene.extent, strategies)
    alive = np.asarray(state.anchors.alive).copy()
    alive[np.flatnonzero(alive)[::2]] = False  # half the anchors pruned
    state = state.replace(anchors=state.anchors.replace(alive=jnp.asarray(alive)))
    keep = np.flatnonzero(alive)
    shrunk = ops.resize_capacity(state, tx, int(np.ceil(len(keep) * 1.5)))
    assert shrunk.anchors.capacity < state.anchors.capacity
    caps = Capacities(visible_fraction=1.0, active_fraction=1.0, pairs_per_active=64.0)
    batch = dict(image=jnp.asarray(scene.images[0].astype(np.float32) / 255.0), camera=Camera.of_scene(scene, 0),
                 index=jnp.int32(0))
    before = jax.device_get(state.anchors.params)
    copy = lambda tree: jax.tree_util.tree_map(jnp.copy, tree)  # noqa: E731  (the step donates its state)
    a, ma = make_train_step(cfg, tx, strategies, caps)(copy(state), batch)
    b, mb = make_train_step(cfg, tx, strategies, caps)(copy(shrunk), batch)
    assert int(ma["dropped_pairs"]) == int(mb["dropped_pairs"]) == 0 and bool(ma["finite"]) and int(a.step) == 1
    np.testing.assert_allclose(float(mb["loss"]), float(ma["loss"]), rtol=1e-6)
    changed = 0
    for (path, x), y, x0 in zip(jax.tree_util.tree_leaves_with_path(a.anchors.params),
                                jax.tree_util.tree_leaves(b.anchors.params),
                                jax.tree_util.tree_leaves(before)):
        np.testing.assert_allclose(np.asarray(y)[:len(keep)], np.asarray(x)[keep], rtol=1e-5, atol=1e-6,
                                   err_msg=jax.tree_util.keystr(path))
        changed += int(np.any(np.asarray(x)[keep] != np.asarray(x0)[keep]))
    assert changed >= 2  # the step did move the alive anchors
    for x, y in zip(jax.tree_util.tree_leaves(a.nets), jax.tree_util.tree_leaves(b.nets)):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-5, atol=1e-6)


def test_shrunk_capacity_rule():
    assert ops.shrunk_capacity(alive=5000, capacity=10000) is None  # half full: kept
    assert ops.shrunk_capacity(alive=3200, capacity=200000) == 6400  # 2 × alive, a multiple of 256
    assert ops.shrunk_capacity(alive=0, capacity=100000) == 256
    # model.capacity_ladder: 2 × alive up to the ladder's rung, the lowest rung 64
    assert ops.shrunk_capacity(alive=3200, capacity=200000, ladder=True) == 7168
    assert ops.shrunk_capacity(alive=0, capacity=100000, ladder=True) == 64
    assert ops.shrunk_capacity(alive=100, capacity=300) is None  # nothing smaller to move to
