"""densify/early_cull.py: the early opacity cull of random starts — its statistics, its rule, when it runs,
and that a run from SfM points does not get it."""

from __future__ import annotations

import types

import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, GrowConfig
from cusgs_jax.compose import compose_config
from cusgs_jax.densify.early_cull import CullStats, EarlyCullStrategy, resolve_early_cull
from cusgs_jax.densify.factory import make_strategies


def _view(slots, valid, opacities, step, finite=True):
    return types.SimpleNamespace(slots=types.SimpleNamespace(slots=jnp.asarray(slots, jnp.int32),
                                                             valid=jnp.asarray(valid)),
                                 gaussians=types.SimpleNamespace(opacities=jnp.asarray(opacities, jnp.float32).reshape(-1)),
                                 step=jnp.int32(step), finite=jnp.asarray(finite))


def test_accumulate_adds_the_decoded_slots_visits_and_positive_opacity_before_the_schedule():
    strategy = EarlyCullStrategy(GrowConfig(start=400))
    stats = strategy.init_state(5)
    # 3 gathered slots of N=2 offsets: slot 4 twice (the second a padding entry), slot 1 once
    opacities = [[0.5, -0.2], [0.1, 0.3], [0.9, 0.9]]
    stats = strategy.accumulate(stats, _view([4, 1, 4], [True, True, False], opacities, step=10))
    np.testing.assert_allclose(stats.visits, [0, 1, 0, 0, 1])
    np.testing.assert_allclose(stats.opacity_accum, [0, 0.4, 0, 0, 0.5], rtol=1e-6)  # max(opacity, 0) summed over N
    same = strategy.accumulate(stats, _view([4, 1, 4], [True, True, True], opacities, step=400))  # schedule's turn
    skipped = strategy.accumulate(stats, _view([4, 1, 4], [True, True, True], [[np.nan] * 2] * 3, step=10,
                                               finite=False))  # a skipped step adds exactly nothing
    for other in (same, skipped):
        np.testing.assert_array_equal(other.visits, stats.visits)
        np.testing.assert_array_equal(other.opacity_accum, stats.opacity_accum)


def _state(alive, visits, opacity):
    anchors = types.SimpleNamespace(alive=jnp.asarray(alive))
    anchors.replace = lambda alive: types.SimpleNamespace(alive=alive, replace=anchors.replace)
    state = types.SimpleNamespace(anchors=anchors, densify={"early_cull": CullStats(jnp.asarray(opacity, jnp.float32),
                                                                                     jnp.asarray(visits, jnp.float32))})
    state.replace = lambda anchors, densify: types.SimpleNamespace(anchors=anchors, densify=densify)
    return state


def test_a_pass_removes_only_anchors_seen_enough_whose_gaussians_stayed_transparent_and_starts_a_new_window():
    cfg = GrowConfig(min_opacity=0.005, early_cull_every=50)  # judged once seen in >= 0.8 * 50 = 40 steps
    strategy = EarlyCullStrategy(cfg)
    alive = [True, True, True, True, False]
    visits = [50, 50, 39, 40, 50]
    opacity = [0.0, 0.3, 0.0, 0.199, 0.0]  # anchor 3: 0.199 < 0.005 * 40 = 0.2 -> transparent
    state, info = strategy.update(_state(alive, visits, opacity), None, 50)
    np.testing.assert_array_equal(state.anchors.alive, [False, True, True, False, False])
    assert info.pruned == 2 and info.extra == dict(alive=2, judged=3) and not info.capacity_changed
    assert not np.any(state.densify["early_cull"].visits) and not np.any(state.densify["early_cull"].opacity_accum)


def test_passes_run_every_early_cull_every_steps_until_the_schedule_takes_over():
    strategy = EarlyCullStrategy(GrowConfig(start=400, early_cull_every=50))
    assert [s for s in range(0, 1000) if strategy.due(s)] == [50, 100, 150, 200, 250, 300, 350]
    with pytest.raises(Exception, match="grow.early_cull"):
        GrowConfig(early_cull="sometimes")


def test_auto_is_on_for_random_starts_not_carved_by_alpha_and_the_strategy_exists_only_when_on():
    cfg = Config()
    assert cfg.grow.early_cull == "auto"
    on, off = resolve_early_cull(cfg, random_start=True), resolve_early_cull(cfg, random_start=False)
    assert (on.grow.early_cull, off.grow.early_cull) == ("on", "off")
    assert resolve_early_cull(cfg, random_start=True, carved_by_coverage=True).grow.early_cull == "off"
    forced = cfg.replace(grow=dict(early_cull="off"))
    assert resolve_early_cull(forced, random_start=True).grow.early_cull == "off"  # a set value is kept
    sized = compose_config(["model.voxel_size=0.01"])
    assert [s.name for s in make_strategies(resolve_early_cull(sized, True))] == ["early_cull", "scaffold", "feature_prune"]
    # SfM points: the same strategies (so the same state and numbers) as before early culling existed
    assert [s.name for s in make_strategies(resolve_early_cull(sized, False))] == ["scaffold", "feature_prune"]
    assert [s.name for s in make_strategies(sized)] == ["scaffold", "feature_prune"]  # unresolved auto: off
