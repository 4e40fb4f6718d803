"""The training state (training/state.py): TrainState, init_train_state, init_nets."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import DEMO_FEATURE_MODELS, Config, FeatureModelConfig
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.densify.feature_prune import PruneStats
from cusgs_jax.densify.scaffold import GrowStats
from cusgs_jax.model.anchors import AnchorState, capacity_rung, voxelize
from cusgs_jax.training.state import TrainState, _draw_nets, init_nets, init_train_state
from cusgs_jax.testing.scenes import random_banks, sfm_points

CFG = Config().replace(train=dict(iterations=50),
                       model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8))
FEATURES = dict(models=(FeatureModelConfig("a", query_dim=4), FeatureModelConfig("b", query_dim=6)), hidden=8)


def _banks():
    return {name: jnp.asarray(b) for name, b in random_banks({"a": (5, 3), "b": (7, 2)}).items()}


def test_fresh_state_from_points():
    strategies = make_strategies(CFG)
    state, tx = init_train_state(CFG, sfm_points(), 3, 2.0, strategies)
    initial = len(voxelize(sfm_points(), CFG.model.voxel_size))
    assert isinstance(state.anchors, AnchorState)
    assert state.anchors.capacity == math.ceil(CFG.model.capacity_factor * initial)
    laddered, _ = init_train_state(CFG.replace(model=dict(capacity_ladder=True)), sfm_points(), 3, 2.0, strategies)
    assert laddered.anchors.capacity == capacity_rung(math.ceil(CFG.model.capacity_factor * initial))
    assert int(np.sum(state.anchors.alive)) == initial and bool(np.all(np.asarray(state.anchors.alive)[:initial]))
    assert state.anchors.params.offsets.shape == (state.anchors.capacity, 4, 3)
    assert state.anchors.params.latent.shape == (state.anchors.capacity, 8)
    assert state.anchors.params.query_table is None
    assert int(state.step) == 0 and int(state.skipped) == 0
    assert set(state.nets) == {"decoder", "appearance"}
    assert state.nets["appearance"].shape == (3, 8)
    # one statistics entry per strategy, sized to the capacity
    assert set(state.densify) == {"scaffold", "feature_prune"}
    assert isinstance(state.densify["scaffold"], GrowStats) and isinstance(state.densify["feature_prune"], PruneStats)
    assert state.densify["scaffold"].grad_accum.shape == (state.anchors.capacity, 4)
    assert state.densify["feature_prune"].contrib.shape == (state.anchors.capacity,)
    # the optimiser state covers exactly the trainable tree
    assert jax.tree_util.tree_structure(tx.init(state.trainable)) == jax.tree_util.tree_structure(state.opt_state)


def test_same_seed_same_state_and_seed_changes_networks():
    strategies = make_strategies(CFG)
    a, _ = init_train_state(CFG, sfm_points(), 2, 2.0, strategies)
    b, _ = init_train_state(CFG, sfm_points(), 2, 2.0, strategies)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)
    c, _ = init_train_state(CFG.replace(train=dict(seed=1)), sfm_points(), 2, 2.0, strategies)
    differs = [not np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(a.nets),
                                                         jax.tree_util.tree_leaves(c.nets))]
    assert any(differs)
    np.testing.assert_array_equal(a.anchors.centers, c.anchors.centers)  # anchors come from the points


def test_trainable_round_trip_and_pytree():
    state, _ = init_train_state(CFG, sfm_points(), 2, 2.0, make_strategies(CFG))
    trainable = state.trainable
    assert set(trainable) == {"anchor", "decoder", "appearance"}
    assert trainable["anchor"] is state.anchors.params
    bumped = jax.tree_util.tree_map(lambda x: x + 1.0, trainable)
    new = state.with_trainable(bumped)
    np.testing.assert_array_equal(new.anchors.params.latent, state.anchors.params.latent + 1.0)
    np.testing.assert_array_equal(new.nets["appearance"], state.nets["appearance"] + 1.0)
    np.testing.assert_array_equal(new.anchors.centers, state.anchors.centers)  # centres are not trainable
    np.testing.assert_array_equal(new.anchors.alive, state.anchors.alive)
    leaves, treedef = jax.tree_util.tree_flatten(state)
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert isinstance(rebuilt, TrainState) and rebuilt.anchors.capacity == state.anchors.capacity
    assert state.replace(step=jnp.int32(7)).step == 7 and state.step == 0  # frozen: replace copies


def test_appearance_off_has_no_embedding():
    cfg = CFG.replace(model=dict(appearance=False))
    nets = init_nets(jax.random.PRNGKey(0), cfg, 4)
    assert set(nets) == {"decoder"}


def test_feature_heads_need_one_bank_per_model():
    cfg = CFG.replace(features=FEATURES)
    with pytest.raises(ValueError, match="PSC bank"):
        init_nets(jax.random.PRNGKey(0), cfg, 2)
    with pytest.raises(ValueError, match="PSC bank"):
        init_nets(jax.random.PRNGKey(0), cfg, 2, {"a": _banks()["a"]})
    nets = init_nets(jax.random.PRNGKey(0), cfg, 2, _banks())
    assert set(nets) == {"decoder", "appearance", "queries", "memory"}
    assert set(nets["memory"]) == {"a", "b"}


def test_per_gaussian_queries_live_in_the_anchor_table():
    cfg = CFG.replace(features=FEATURES, model=dict(query_granularity="per_gaussian"))
    state, _ = init_train_state(cfg, sfm_points(), 2, 2.0, make_strategies(cfg), _banks())
    assert "queries" not in state.nets and set(state.nets["memory"]) == {"a", "b"}
    assert state.anchors.params.query_table.shape == (state.anchors.capacity, 4, 10)


def test_a_scaffold_of_a_few_anchors_is_refused_and_a_coarse_one_warned_about(caplog):
    from cusgs_jax.errors import ConfigError

    points = sfm_points()
    with pytest.raises(ConfigError, match=r"model\.voxel_size=1000\.0: leaves only 1 anchor\(s\) for 400 initial "
                                          r"points.*model\.voxel_size=auto \(here "):
        init_train_state(CFG.replace(model=dict(voxel_size=1000.0)), points, 2, 1.0, ())
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        state, _ = init_train_state(CFG.replace(model=dict(voxel_size=1.0)), points, 2, 1.0, ())
    assert 4 <= int(np.sum(state.anchors.alive)) < 64 and "the model will be very coarse" in caplog.text
    assert "SfM" not in caplog.text and "model.voxel_size=auto (here" in caplog.text
    with pytest.raises(ConfigError, match="resolve_voxel_size"):
        init_train_state(CFG.replace(model=dict(voxel_size=None)), points, 2, 1.0, ())


def test_too_few_initial_points_are_blamed_not_the_cell_and_auto_is_not_suggested_when_set(caplog):
    """A random start that carving left with a handful of points (issue 47: 5 of 100 000) gets about one anchor
    per point at any small cell: the hint names the carving, not model.voxel_size=auto."""
    from cusgs_jax.errors import ConfigError
    from cusgs_jax.model.anchors import auto_voxel_size

    points = np.random.default_rng(0).uniform(-0.5, 0.5, size=(20, 3))
    for voxel_size in (0.002, auto_voxel_size(points)):  # the random start's auto cell; the points' own spacing
        caplog.clear()
        with caplog.at_level("WARNING", logger="cusgs_jax"):
            state, _ = init_train_state(CFG.replace(model=dict(voxel_size=voxel_size)), points, 2, 1.0, ())
        assert 10 <= int(np.sum(state.anchors.alive)) <= 20
        assert "from 20 initial points" in caplog.text and "too few initial points" in caplog.text
        assert "carving" in caplog.text and "data.carve=none" in caplog.text
        assert "voxel_size=auto" not in caplog.text and "SfM" not in caplog.text
    with pytest.raises(ConfigError, match=r"leaves only 3 anchor\(s\) for 3 initial points; there are too few "
                                          r"initial points") as refused:
        init_train_state(CFG.replace(model=dict(voxel_size=0.002)), points[:3], 2, 1.0, ())
    assert "voxel_size=auto" not in str(refused.value) and "as large as the scene" not in str(refused.value)


def test_auto_voxel_size_is_the_median_spacing_and_scales_with_the_scene():
    from cusgs_jax.model.anchors import auto_voxel_size

    points = sfm_points()
    assert auto_voxel_size(1000.0 * points + 7.0) == pytest.approx(1000.0 * auto_voxel_size(points), rel=1e-9)
    grid = np.stack(np.meshgrid(*[np.arange(5.0)] * 3), -1).reshape(-1, 3) * 0.3  # spacing 0.3
    assert auto_voxel_size(np.concatenate([grid, grid])) == pytest.approx(0.3)  # duplicates ignored


@pytest.mark.parametrize("granularity, adapter", [("per_anchor", "affine"), ("per_gaussian", "lowrank")])
def test_the_networks_are_one_program_drawing_what_draws_one_call_at_a_time_give(granularity, adapter, compiles):
    """``init_nets`` draws every network in one program, bit for bit what its body gives run call by call
    (``_draw_nets.__wrapped__``: each draw and division its own program, as the networks were drawn before), for
    the demo run's exact shapes (latent 32, hidden 32, N = 10, 26 training views, banks of 104-, 32- and
    256-D features: dimensions whose square roots are not exact, where XLA merged a division into the draw)."""
    models = tuple(dataclasses.replace(m, adapter=adapter) for m in DEMO_FEATURE_MODELS)
    cfg = Config().replace(features=dict(models=models), model=dict(query_granularity=granularity))
    banks = {"daisy": np.zeros((263, 104), np.float32), "semantic": np.zeros((16, 32), np.float32),
             "vgg16": np.zeros((838, 256), np.float32)}
    key = jax.random.PRNGKey(0)
    before = compiles.count()
    nets = init_nets(key, cfg, 26, banks)
    assert compiles.count() - before == 1 and compiles.count("jit(_draw_nets)") >= 1
    eager = _draw_nets.__wrapped__(key, cfg, 26, tuple(sorted((n, b.shape) for n, b in banks.items())))
    got, want = jax.tree_util.tree_leaves_with_path(nets), jax.tree_util.tree_leaves_with_path(eager)
    assert [p for p, _ in got] == [p for p, _ in want] and len(got) > 20
    for (path, a), (_, b) in zip(got, want):
        np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
