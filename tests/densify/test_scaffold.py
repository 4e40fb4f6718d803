"""Scaffold-GS growing and opacity pruning on masks (the ``scaffold`` densification strategy)."""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import GrowConfig, OptimConfig
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import UpdateInfo, ViewRecord
from cusgs_jax.densify.scaffold import GrowStats, ScaffoldStrategy, accumulate_stats, opacity_prune, plan_growth
from cusgs_jax.model.anchors import AnchorParams, AnchorState, capacity_rung
from cusgs_jax.model.decode import VisibleSlots
from cusgs_jax.training.optim import make_optimizer
from cusgs_jax.training.state import TrainState


class _AlwaysKeep:
    """Stands in for np.random.Generator: every random draw is 1 (keep every candidate)."""

    def random(self, shape):
        return np.ones(shape)


@pytest.fixture
def always_keep(monkeypatch):
    """Every ScaffoldStrategy's candidate draws keep every candidate."""
    monkeypatch.setattr(ScaffoldStrategy, "generator", lambda self, step: _AlwaysKeep())


def _anchors(capacity=8, alive=3, n=2, offsets=None) -> AnchorState:
    centers = np.zeros((capacity, 3), np.float32)
    centers[:alive] = np.arange(alive)[:, None] * np.array([1.0, 0, 0])
    params = AnchorParams(offsets=jnp.zeros((capacity, n, 3)) if offsets is None else jnp.asarray(offsets),
                          log_scaling=jnp.zeros((capacity, 6)),
                          latent=jnp.asarray(np.arange(capacity * 4, dtype=np.float32).reshape(capacity, 4)))
    return AnchorState(jnp.asarray(centers), jnp.asarray(np.arange(capacity) < alive), params)


def _train_state(anchors: AnchorState, stats: GrowStats):
    """A TrainState with only the anchors trainable, and its optimiser."""
    tx = make_optimizer(OptimConfig(), {"anchor": anchors.params}, 100, 1.0)
    state = TrainState(anchors=anchors, nets={}, opt_state=tx.init({"anchor": anchors.params}),
                       densify={"scaffold": stats}, step=jnp.int32(0), skipped=jnp.int32(0))
    return state, tx


def test_accumulate_stats_formula():
    stats = GrowStats.zeros(2, 2)
    grad = jnp.array([[[0.1, 0.0], [0.0, 0.2]], [[1.0, 1.0], [0.0, 0.0]]])
    out = accumulate_stats(stats, jnp.array([True, False]), jnp.array([[0.5, -0.2], [0.9, 0.9]]),
                           jnp.array([[True, False], [False, False]]), grad, 100, 50, jnp.array(True))
    np.testing.assert_allclose(out.grad_accum, [[0.1 * 50, 0], [0, 0]], rtol=1e-6)
    np.testing.assert_allclose(out.grad_count, [[1, 0], [0, 0]])
    np.testing.assert_allclose(out.opacity_accum, [0.5, 0.0])
    np.testing.assert_allclose(out.visits, [1, 0])
    off = accumulate_stats(stats, jnp.array([True, True]), jnp.ones((2, 2)), jnp.ones((2, 2), bool), grad,
                           100, 50, jnp.array(False))
    assert float(jnp.sum(off.visits)) == 0.0


def test_strategy_accumulate_scatters_gathered_views_to_slots():
    """The step's hook: gathered entries [S] go to their slots [A]; padding entries add nothing."""
    capacity, n = 6, 2
    strategy = ScaffoldStrategy(GrowConfig(stats_start=10, stop=20), 1.0, n, 0)
    slots = VisibleSlots(jnp.array([4, 1, 0], jnp.int32), jnp.array([True, True, False]), jnp.int32(0))
    opacities = jnp.array([0.3, -0.1, 0.6, 0.2, 0.9, 0.9])
    gaussians = types.SimpleNamespace(opacities=opacities, active=opacities > 0)
    render = types.SimpleNamespace(visible=jnp.array([True, True, False, True, True, True]))
    grad2d = jnp.arange(12.0).reshape(6, 2) * 0.01

    def record(step, finite=True):
        return ViewRecord(slots=slots, gaussians=gaussians, render=render, grad2d=grad2d,
                          latent_grad=jnp.zeros((3, 4)), capacity=capacity, width=8, height=6,
                          step=jnp.int32(step), finite=jnp.asarray(finite))

    stats = strategy.accumulate(strategy.init_state(capacity), record(12))
    anchor_visible = np.zeros(capacity, bool)
    anchor_visible[[4, 1]] = True
    full_opacity = np.zeros((capacity, n), np.float32)
    full_opacity[[4, 1]] = np.asarray(opacities).reshape(3, n)[:2]
    seen = np.zeros((capacity, n), bool)
    seen[4] = [True, False]  # opacity -0.1 is switched off
    seen[1] = [False, True]  # not rasterised (visible False)
    full_grad = np.zeros((capacity, n, 2), np.float32)
    full_grad[[4, 1]] = np.asarray(grad2d).reshape(3, n, 2)[:2]
    want = accumulate_stats(GrowStats.zeros(capacity, n), jnp.asarray(anchor_visible), jnp.asarray(full_opacity),
                            jnp.asarray(seen), jnp.asarray(full_grad), 8, 6, jnp.array(True))
    for got, expect in zip(jax.tree_util.tree_leaves(stats), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(got, expect, rtol=1e-6)
    np.testing.assert_array_equal(stats.visits, [0, 1, 0, 0, 1, 0])
    # outside [stats_start, stop) or with a non-finite update nothing is added
    for step, finite in ((9, True), (20, True), (12, False)):
        off = strategy.accumulate(strategy.init_state(capacity), record(step, finite))
        assert not any(np.any(np.asarray(x)) for x in jax.tree_util.tree_leaves(off)), (step, finite)


def test_growing_fills_dead_slots_in_unoccupied_cells(always_keep):
    cfg = GrowConfig(interval=10, levels=1, init_factor=1, hierarchy_factor=4)
    offsets = np.zeros((8, 2, 3), np.float32)
    offsets[0, 0] = [0.0, 0.0, 3.0]  # Gaussian of anchor 0 at (0,0,3): an empty cell
    offsets[1, 1] = [1.0, 0.0, 0.0]  # at (2,0,0): occupied by anchor 2 → no new anchor
    anchors = _anchors(offsets=offsets)
    stats = GrowStats(grad_accum=jnp.full((8, 2), 0.01) * 10, grad_count=jnp.full((8, 2), 10.0),
                      opacity_accum=jnp.ones(8), visits=jnp.ones(8))
    state, tx = _train_state(anchors, stats)
    new_state, info = ScaffoldStrategy(cfg, 1.0, 2, 0).update(state, tx, 10)
    new_anchors, new_params, new_stats = new_state.anchors, new_state.anchors.params, new_state.densify["scaffold"]
    alive = np.asarray(new_anchors.alive)
    assert isinstance(info, UpdateInfo) and info.grown == 1 and alive.sum() == 4
    slot = 3
    np.testing.assert_allclose(new_anchors.centers[slot], [0, 0, 3])
    np.testing.assert_allclose(new_params.latent[slot], anchors.params.latent[0])  # max over its one parent
    np.testing.assert_allclose(new_params.offsets[slot], 0)
    np.testing.assert_allclose(new_params.log_scaling[slot], 0.0)  # log(cell = 1)
    assert float(jnp.sum(new_stats.grad_count[:3])) == 0.0  # participating Gaussians reset
    assert info.extra["capacity"] == 8 and not info.capacity_changed and info.extra["alive"] == 4


def test_plan_growth_levels_and_occupied_cells():
    """Two levels: level 1 uses cells init_factor/hierarchy_factor times smaller and a doubled threshold."""
    cfg = GrowConfig(interval=10, levels=2, init_factor=4, hierarchy_factor=4, grad_threshold=0.1)
    offsets = np.zeros((8, 2, 3), np.float32)
    offsets[0, 0] = [0.0, 0.0, 8.0]  # (0,0,8): an empty cell of size 4 → grown at level 0
    # anchor 1's two Gaussians at (1,0,1): its size-4 cell (0,0,0) is taken by anchor 0, its size-1
    # cell is empty → one anchor grown at level 1 from two candidates
    offsets[1, :] = [0.0, 0.0, 1.0]
    anchors = _anchors(offsets=offsets)
    grad = np.full((8, 2), 0.15, np.float32)  # ≥ 0.1 (level 0), < 0.2 (level 1) ...
    grad[1] = 0.25  # ... except anchor 1's Gaussians, which pass level 1 too
    stats = GrowStats(jnp.asarray(grad * 10), jnp.full((8, 2), 10.0), jnp.ones(8), jnp.ones(8))
    centers, latents, log_cells, took_part = plan_growth(anchors, stats, cfg, 1.0, _AlwaysKeep())
    np.testing.assert_allclose(centers, [[0, 0, 8], [1, 0, 1]])
    np.testing.assert_allclose(latents, np.asarray(anchors.params.latent)[[0, 1]])
    np.testing.assert_allclose(log_cells, np.log([4.0, 1.0]))
    assert took_part.shape == (8, 2) and took_part.all()  # 10 visits > 10 · 0.8 · 0.5
    nothing = plan_growth(anchors, GrowStats.zeros(8, 2), cfg, 1.0, _AlwaysKeep())
    assert [x.shape for x in nothing] == [(0, 3), (0, 4), (0,), (8, 2)] and not nothing[3].any()


def test_pruning_removes_seasoned_transparent_anchors(always_keep):
    cfg = GrowConfig(interval=100, min_opacity=0.005)
    anchors = _anchors()
    stats = GrowStats(grad_accum=jnp.zeros((8, 2)), grad_count=jnp.zeros((8, 2)),
                      opacity_accum=jnp.array([0.1, 10.0, 0.1, 0, 0, 0, 0, 0]),
                      visits=jnp.array([100.0, 100.0, 50.0, 0, 0, 0, 0, 0]))
    state, tx = _train_state(anchors, stats)
    new_state, info = ScaffoldStrategy(cfg, 1.0, 2, 0).update(state, tx, 100)
    new_anchors, new_stats = new_state.anchors, new_state.densify["scaffold"]
    np.testing.assert_array_equal(np.asarray(new_anchors.alive)[:3], [False, True, True])
    assert info.pruned == 1
    np.testing.assert_allclose(new_stats.visits[:3], [0, 0, 50])  # seasoned ones reset
    # the pure function agrees
    prune, direct = opacity_prune(np.asarray(anchors.alive), stats, cfg)
    np.testing.assert_array_equal(prune, [True] + [False] * 7)
    for x, y in zip(jax.tree_util.tree_leaves(direct), jax.tree_util.tree_leaves(new_stats)):
        np.testing.assert_array_equal(x, y)


def test_capacity_grows_when_full(always_keep):
    cfg = GrowConfig(interval=10, levels=1, init_factor=1, capacity_growth=1.5)
    offsets = np.zeros((3, 2, 3), np.float32)
    offsets[:, 0, 2] = [5.0, 6.0, 7.0]
    anchors = _anchors(capacity=3, alive=3, offsets=offsets)
    stats = GrowStats(jnp.full((3, 2), 1.0), jnp.full((3, 2), 10.0), jnp.ones(3), jnp.ones(3))
    state, tx = _train_state(anchors, stats)
    state = state.replace(opt_state=ops.map_moments(tx, jnp.ones_like, state.opt_state))  # non-zero moments
    new_state, info = ScaffoldStrategy(cfg, 1.0, 2, 0).update(state, tx, 10)
    new_params, new_anchors, new_opt = new_state.anchors.params, new_state.anchors, new_state.opt_state
    assert info.capacity_changed and info.extra["capacity"] >= 6
    assert new_params.latent.shape[0] == info.extra["capacity"] == new_anchors.alive.shape[0]
    assert int(np.sum(new_anchors.alive)) == 6
    moments = [(jax.tree_util.keystr(p), np.asarray(x)) for p, x in jax.tree_util.tree_leaves_with_path(new_opt)
               if "['anchor']" in jax.tree_util.keystr(p)]
    assert len(moments) == 6  # Adam's mu and nu of offsets, log_scaling, latent
    for name, mu in moments:
        assert mu.shape[0] == info.extra["capacity"], name
        # the new slots' optimiser moments start at zero; the old anchors keep theirs
        assert float(np.sum(mu[3:])) == 0.0, name
        np.testing.assert_array_equal(mu[:3], 1.0, err_msg=name)
    for x in jax.tree_util.tree_leaves(new_state.densify):
        assert x.shape[0] == info.extra["capacity"]


def test_schedule():
    strategy = ScaffoldStrategy(GrowConfig(start=400, stop=1500, interval=100), 1.0, 2, 0)
    assert [s for s in range(0, 2001, 50) if strategy.due(s)] == list(range(400, 1501, 100))


def test_accumulate_rows_equals_the_dense_statistics_and_ignores_nan_of_skipped_steps():
    """The O(S) hook adds what scattering to [A] and the dense formula add; a disabled call with
    non-finite inputs adds exactly 0 (random inputs, padding entries repeating a slot)."""
    from cusgs_jax.densify.scaffold import accumulate_rows

    rng = np.random.default_rng(0)
    capacity, n, s = 9, 3, 5
    slots = np.array([7, 2, 5, 2, 2], np.int32)
    valid = np.array([True, True, True, False, False])
    opacities = rng.normal(size=(s, n)).astype(np.float32)
    visible = rng.random((s, n)) > 0.3
    grad2d = rng.normal(size=(s, n, 2)).astype(np.float32)
    start = GrowStats(*(jnp.asarray(rng.random(x.shape), jnp.float32) for x in
                        jax.tree_util.tree_leaves(GrowStats.zeros(capacity, n))))
    got = accumulate_rows(start, jnp.asarray(slots), jnp.asarray(valid), jnp.asarray(opacities), jnp.asarray(visible),
                          jnp.asarray(grad2d), 16, 12, jnp.array(True))
    dense = [np.zeros((capacity,) + x.shape[1:], x.dtype) for x in (valid, opacities, visible, grad2d)]
    for x, d in zip((valid, opacities, visible, grad2d), dense):
        d[slots[valid]] = x[valid]
    want = accumulate_stats(start, *(jnp.asarray(d) for d in dense), 16, 12, jnp.array(True))
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    bad = accumulate_rows(start, jnp.asarray(slots), jnp.asarray(valid), jnp.full((s, n), np.nan), jnp.asarray(visible),
                          jnp.full((s, n, 2), np.inf), 16, 12, jnp.array(False))
    for a, b in zip(jax.tree_util.tree_leaves(bad), jax.tree_util.tree_leaves(start)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("ladder, grown", [(False, 96), (True, 128)])
def test_a_full_capacity_grows_as_forecast_on_or_off_the_ladder(always_keep, ladder, grown):
    # 64 full slots, growth 1.5: ceil(96), with model.capacity_ladder its rung 128; next_capacity forecasts it
    cfg = GrowConfig(interval=10, levels=1, init_factor=1, capacity_growth=1.5, stop=100)
    offsets = np.zeros((64, 2, 3), np.float32)
    offsets[:16, 0, 2] = np.arange(16) + 5.0  # 16 new anchors: 80 alive, fewer than ceil(1.5 · 64)
    anchors = _anchors(capacity=64, alive=64, offsets=offsets)
    stats = GrowStats(jnp.full((64, 2), 1.0), jnp.full((64, 2), 10.0), jnp.ones(64), jnp.ones(64))
    state, tx = _train_state(anchors, stats)
    strategy = ScaffoldStrategy(cfg, 1.0, 2, 0, ladder=ladder)
    forecast = strategy.next_capacity(state, 10)
    _, info = strategy.update(state, tx, 10)
    assert info.capacity_changed and info.extra["capacity"] == forecast == grown
    assert not ladder or grown == capacity_rung(96)
    assert strategy.next_capacity(state, 100) is None  # growth has stopped: nothing to forecast
