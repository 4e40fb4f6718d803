"""The jitted train step (training/step.py) with the densification strategies (densify/base.py):
compiles once, deterministic, skips non-finite updates, feature-aware pruning statistics and passes."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy, anchor_scores, prune_due
from cusgs_jax.model.anchors import compact
from cusgs_jax.model.decode import decode_view, num_visible_slots
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.render import make_render_fn, render_gaussians, render_model
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.optim import make_optimizer
from cusgs_jax.training.step import make_train_step, step_settings
from cusgs_jax.types import Camera
from cusgs_jax.testing.scenes import sfm_points

W, H = 32, 24
K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])


def _cfg(**grow):
    return Config().replace(
        train=dict(iterations=50),
        model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
        grow={**dict(stats_start=0, start=5, stop=50, interval=5), **grow})


def _batch(seed=0, nan=False):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    if nan:
        image[3, 4, 1] = np.nan
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = rng.normal(0, 0.05, 3)
    return dict(image=jnp.asarray(image), camera=Camera(K, jnp.asarray(view), W, H), index=jnp.int32(seed % 2))


def _init(cfg):
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies)
    return strategies, state, tx


@pytest.fixture(scope="module")
def setup():
    cfg = _cfg(grad_threshold=0.0, min_opacity=0.2, success_threshold=0.8)
    strategies, state, tx = _init(cfg)
    return cfg, tx, strategies, make_train_step(cfg, tx, strategies), state


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)


def _scaffold(strategies):
    (strategy,) = [s for s in strategies if s.name == "scaffold"]
    return strategy


def test_make_strategies_follows_the_prune_strategy():
    assert [s.name for s in make_strategies(_cfg())] == ["scaffold", "feature_prune"]
    for name in ("scaffold", "none"):
        assert [s.name for s in make_strategies(_cfg().replace(prune=dict(strategy=name)))] == ["scaffold"]


def test_step_compiles_once_across_growing_and_pruning(setup, compiles):
    cfg, tx, strategies, step, state = setup
    state = _copy(state)
    scaffold = _scaffold(strategies)
    grown = pruned = adjustments = 0
    for i in range(20):
        state, metrics = step(state, _batch(i))
        if (i + 1) % cfg.grow.interval == 0:
            assert scaffold.due(i + 1)
            state, info = scaffold.update(state, tx, i + 1)
            assert not info.capacity_changed
            grown += info.grown
            pruned += info.pruned
            adjustments += 1
        else:
            assert not scaffold.due(i + 1)
    assert adjustments == 4
    assert grown > 0 and pruned > 0  # the masks really changed
    assert compiles.count("jit(train_step)") <= 1  # at most the first call's (the fixture's step may be compiled)
    assert int(state.step) == 20 and bool(metrics["finite"])


def test_same_seed_same_numbers(setup):
    cfg, tx, strategies, step, state0 = setup
    finals = []
    for _ in range(2):
        state = _copy(state0)
        for i in range(3):
            state, metrics = step(state, _batch(i))
        finals.append((jax.device_get(state.trainable), float(metrics["loss"])))
    assert finals[0][1] == finals[1][1]
    leaves_a, leaves_b = (jax.tree_util.tree_leaves(f[0]) for f in finals)
    assert len(leaves_a) == len(leaves_b) > 0
    for a, b in zip(leaves_a, leaves_b):
        np.testing.assert_array_equal(a, b)


WEIGHTED = dict(loss=dict(l1_weight=0.55, ssim_weight=0.45, volume_weight=0.3))


def _settings(cfg, extent=2.0) -> dict:
    """The batch entries that make settings arguments, as ``make_batches`` gives them (``extent`` as ``_init``)."""
    return step_settings(cfg, extent)


@pytest.mark.slow  # two step programs compiled (27 s); the lowered-program test below stays in the default run
def test_loss_weights_and_seed_in_the_batch_give_the_numbers_of_constants_folded_in(setup):
    """The loop passes the loss weights, the seed's key and the learning rates as arguments
    (``batch["loss_weights"]``, ``batch["seed_key"]``, ``batch["learning_rates"]``); the step's numbers are those
    of the same settings as the program's constants (a batch without them), bit for bit, over three steps (the
    decaying and the constant learning-rate groups both move)."""
    cfg0, tx, strategies, _, state0 = setup
    cfg = cfg0.replace(**WEIGHTED)
    step = make_train_step(cfg, tx, strategies)
    finals = []
    for given in (False, True):
        state = _copy(state0)
        for i in range(3):
            batch = dict(_batch(i), **_settings(cfg)) if given else _batch(i)
            state, metrics = step(state, batch)
        finals.append(jax.device_get((state.trainable, state.densify, metrics)))
    for a, b in zip(*(jax.tree_util.tree_leaves(f) for f in finals)):
        np.testing.assert_array_equal(a, b)
    terms = finals[1][2]  # and they are the weights the loss was made of
    np.testing.assert_allclose(terms["loss"], 0.55 * terms["loss_l1"] + 0.45 * terms["loss_ssim_loss"]
                               + 0.3 * terms["loss_volume"], rtol=1e-6)


def test_a_sweep_over_loss_weights_learning_rates_or_seeds_shares_one_step_program(setup):
    """Configurations that differ only in ``loss.*_weight``, ``features.weight``, ``optim.*`` learning rates or
    ``train.seed`` lower the same step (one persistent-cache entry); the batch and the optimiser are what the loop
    gives (``make_batches``, ``init_train_state``)."""
    cfg0, _, strategies, _, state0 = setup

    def lowered(cfg):
        tx = make_optimizer(cfg.optim, state0.trainable, cfg.train.iterations, 2.0)
        return make_train_step(cfg, tx, strategies).lower(state0, dict(_batch(0), **_settings(cfg))).as_text()

    base = lowered(cfg0)
    assert lowered(cfg0.replace(**WEIGHTED)) == base
    assert lowered(cfg0.replace(features=dict(weight=0.9), train=dict(seed=7))) == base
    assert lowered(cfg0.replace(optim=dict(offsets=(0.02, 0.0002), mlp_color=(0.004, 0.0001)))) == base
    # a group whose rate stops decaying (initial = final) changes the program; so does the schedule's length
    assert lowered(cfg0.replace(optim=dict(offsets=(0.01, 0.01)))) != base
    assert lowered(cfg0.replace(train=dict(iterations=60))) != base


def test_non_finite_update_is_skipped_and_counted(setup):
    cfg, tx, strategies, step, state0 = setup
    state, _ = step(_copy(state0), _batch(0))
    before = jax.device_get((state.trainable, state.opt_state))
    state, metrics = step(state, _batch(1, nan=True))
    assert not bool(metrics["finite"]) and int(state.skipped) == 1
    after = jax.device_get((state.trainable, state.opt_state))
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a, b)
    state, metrics = step(state, _batch(2))
    assert bool(metrics["finite"]) and int(state.skipped) == 1


def test_dead_anchors_do_not_move(setup):
    cfg, tx, strategies, step, state0 = setup
    state = _copy(state0)
    alive = np.array(state.anchors.alive)
    alive[:5] = False
    state = state.replace(anchors=state.anchors.replace(alive=jnp.asarray(alive)))
    before = jax.device_get(state.anchors.params)
    for i in range(2):
        state, _ = step(state, _batch(i))
    after = jax.device_get(state.anchors.params)
    moved = False
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a[:5], b[:5])
        moved |= not np.array_equal(a[alive], b[alive])
    assert moved


# ---------------------------------------------------------------- feature-aware pruning in training

def _prune_cfg(**prune):
    base = {"strategy": "feature_aware", "ratio": 0.1, "interval": 3, "start": 3, "stop": 50, "min_visits": 0}
    return _cfg().replace(prune={**base, **prune})


def _prune_strategy(strategies) -> FeaturePruneStrategy:
    (strategy,) = [s for s in strategies if s.name == FeaturePruneStrategy.name]
    return strategy


@pytest.fixture(scope="module")
def prune_setup():
    cfg = _prune_cfg()
    strategies, state, tx = _init(cfg)
    return cfg, tx, make_train_step(cfg, tx, strategies), _prune_strategy(strategies), state


def _train_render(cfg):
    """The train step's own decode → rasterise path (visible_fraction < 1, no compaction)."""

    @jax.jit
    def render(anchors, nets, camera, index):
        out, _, _ = render_model(anchors, nets, camera, index, cfg, Capacities.from_config(cfg))
        return jnp.clip(out.image, 0.0, 1.0)

    return render


@pytest.mark.slow
def test_prune_statistics_equal_a_direct_float64_computation(prune_setup):
    """One step's PruneStats against a direct computation: autodiff of the same loss for ∇z, the
    float64 reference rasteriser for Σ opacity·T, and testing.prune_reference for the score."""
    from cusgs_jax import losses
    from cusgs_jax.testing.splat_reference import rasterize_reference
    from cusgs_jax.testing.prune_reference import significance_reference

    cfg, tx, step, _, state0 = prune_setup
    batch = _batch(3)
    camera = batch["camera"]
    trainable, anchors = jax.device_get(state0.trainable), state0.anchors

    def loss_of(p):
        g, view = decode_view(p, anchors.replace(params=p["anchor"]), camera, batch["index"], cfg.model,
                              num_visible_slots(anchors.capacity, cfg.model.visible_fraction))
        out, _ = render_gaussians(g, camera, cfg.splat)
        loss, _ = losses.image_loss(out.image, batch["image"], g.scales, g.active, l1_weight=cfg.loss.l1_weight,
                                    ssim_weight=cfg.loss.ssim_weight, volume_weight=cfg.loss.volume_weight)
        return loss, (g, view)

    grads, (g, view) = jax.grad(loss_of, has_aux=True)(trainable)
    slots, valid = np.asarray(view.slots), np.asarray(view.valid)
    reference = rasterize_reference(np.asarray(g.means), np.asarray(g.quats), np.asarray(g.scales),
                                    np.asarray(g.opacities), np.asarray(g.colors),
                                    np.asarray(camera.world_to_camera), np.asarray(camera.K), W, H)
    record = {"slots": slots, "valid": valid,
              "latent_grad": np.asarray(grads["anchor"].latent)[slots],
              "significance": reference["significance"], "scales": np.asarray(g.scales),
              "active": np.asarray(g.active)}
    state, _ = step(_copy(state0), batch)
    stats = state.densify[FeaturePruneStrategy.name]
    latent = np.asarray(state.anchors.params.latent)
    alive = np.asarray(state.anchors.alive)
    expected = significance_reference(latent, alive, [record], cfg.prune)
    got = np.asarray(anchor_scores(state.anchors.params.latent, stats, state.anchors.alive, cfg.prune))
    assert np.sum(np.asarray(stats.contrib) > 0) > 10  # the view really touched many anchors
    np.testing.assert_array_equal(np.isinf(got), np.isinf(expected))
    np.testing.assert_allclose(got[alive], expected[alive], rtol=2e-4, atol=1e-5)
    seen = np.zeros(len(alive), bool)
    seen[slots[valid]] = True
    np.testing.assert_array_equal(np.asarray(stats.grad_count), seen.astype(np.float32))


@pytest.mark.slow  # 27 s on 2 cores: kept out of the default run; .ci/run's -m slow pass runs it
def test_prune_pass_honours_ratio_and_pruned_anchors_are_inert(prune_setup, compiles):
    cfg, tx, step, prune, state0 = prune_setup
    state = _copy(state0)
    for i in range(3):
        state, _ = step(state, _batch(i))
    assert prune.due(int(state.step))
    alive_before = np.array(state.anchors.alive)
    state, info = prune.update(state, tx, int(state.step))
    alive_after = np.array(state.anchors.alive)
    removed = alive_before & ~alive_after
    assert info.pruned == removed.sum() == int(0.1 * alive_before.sum()) > 0
    assert not np.any(alive_after & ~alive_before)
    assert float(jnp.sum(state.densify[prune.name].contrib)) == 0.0  # statistics restart after a pass

    # pruned anchors contribute nothing: the render equals the render of the model without them ...
    batch = _batch(5)
    camera, index = batch["camera"], batch["index"]
    train_render = _train_render(cfg)
    image = train_render(state.anchors, state.nets, camera, index)
    compact_anchors = compact(state.anchors)
    assert compact_anchors.capacity < state.anchors.capacity
    render = make_render_fn(cfg)  # every slot decoded
    (compact_image,) = render(compact_anchors, state.nets, camera, index)
    np.testing.assert_allclose(np.asarray(image), np.asarray(compact_image), atol=1e-6)
    (full_image,) = render(state.anchors, state.nets, camera, index)
    np.testing.assert_allclose(np.asarray(full_image), np.asarray(compact_image), atol=1e-6)

    # ... their parameters get exactly zero gradient and do not move in later steps
    def image_sum(anchor_params):
        return jnp.sum(train_render(state.anchors.replace(params=anchor_params), state.nets, camera, index))

    grad = jax.grad(image_sum)(state.anchors.params)
    for leaf in jax.tree_util.tree_leaves(grad):
        assert np.all(np.asarray(leaf)[removed] == 0)
    before = jax.device_get(state.anchors.params)
    for i in range(3):
        state, _ = step(state, _batch(10 + i))
    after = jax.device_get(state.anchors.params)
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(a[removed], b[removed])
    # masks, not new shapes: at most the first call's program of each (the fixture's step may be compiled)
    assert compiles.count("jit(train_step)") <= 1 and compiles.count("jit(pruning_pass)") <= 1


def test_prune_ratio_counts_exactly_and_repeated_passes_do_not_recompile(prune_setup, compiles):
    cfg, tx, step, prune, state0 = prune_setup
    state = _copy(state0)
    counts = [int(np.sum(state.anchors.alive))]
    for i in range(12):
        state, _ = step(state, _batch(i))
        done = int(state.step)
        assert prune.due(done) == prune_due(done, cfg.prune)
        if prune_due(done, cfg.prune):
            state, info = prune.update(state, tx, done)
            counts.append(info.extra["alive"])
    assert len(counts) == 5  # passes at steps 3, 6, 9, 12
    for before, after in zip(counts, counts[1:]):
        assert after == before - before // 10
    assert compiles.count("jit(train_step)") <= 1 and compiles.count("jit(pruning_pass)") <= 1


@pytest.mark.slow
def test_strategy_none_keeps_every_anchor_and_collects_nothing():
    cfg = _prune_cfg(strategy="none")
    strategies, state, tx = _init(cfg)
    # no feature-aware strategy is built: nothing is traced, collected or stored for it
    assert [s.name for s in strategies] == ["scaffold"] and set(state.densify) == {"scaffold"}
    step = make_train_step(cfg, tx, strategies)
    alive = np.array(state.anchors.alive)
    for i in range(3):
        state, _ = step(state, _batch(i))
    assert set(state.densify) == {"scaffold"}
    assert not any(prune_due(s, cfg.prune) for s in range(cfg.train.iterations + 1))
    # a pass with strategy "none" removes nothing (the statistics it would read are all zero)
    prune = FeaturePruneStrategy(cfg.prune)
    state = state.replace(densify={**state.densify, prune.name: prune.init_state(state.anchors.capacity)})
    assert all(float(jnp.sum(x)) == 0.0 for x in jax.tree_util.tree_leaves(state.densify[prune.name]))
    state, info = prune.update(state, tx, 3)
    assert info.pruned == 0
    np.testing.assert_array_equal(np.asarray(state.anchors.alive), alive)


@pytest.mark.slow  # three step compiles (~30 s): in .ci/run's -m slow pass
def test_the_tile_pairs_capacity_changes_nothing_and_the_active_one_only_an_order_of_summation():
    """What Capacities.regrown relies on. With the visible slots fixed, a step whose capacities hold its view gives,
    bit for bit, the state of one with room for 50 tile pairs per active Gaussian (the splatter sorts the valid
    pairs alike); with more active-Gaussian slots (arrays of another length) it agrees to float rounding only."""
    cfg = _cfg()
    strategies, state, tx = _init(cfg)
    tight = Capacities(visible_fraction=1.0, active_fraction=0.5, pairs_per_active=6.0)
    results = []
    for caps in (tight, dataclasses.replace(tight, pairs_per_active=50.0), dataclasses.replace(tight, active_fraction=0.875)):
        step, current = make_train_step(cfg, tx, strategies, caps), _copy(state)
        for seed in range(3):
            current, metrics = step(current, _batch(seed))
            assert not (int(metrics["dropped_anchors"]) or int(metrics["dropped_gaussians"]) or int(metrics["dropped_pairs"]))
        assert 0 < int(metrics["active_gaussians"])
        results.append(jax.tree_util.tree_leaves(current))
    for a, more_pairs, more_active in zip(*results):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(more_pairs))
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(more_active, np.float64), rtol=1e-5, atol=1e-6)


@pytest.mark.slow  # ~36 s (seven step compiles): in .ci/run's -m slow pass; the default run keeps the
# batched overflow test below and test_view_render's pair-growth test
def test_a_step_that_would_drop_work_changes_nothing_and_the_grown_replay_is_exact(monkeypatch):
    """Too few visible slots, active Gaussians and tile pairs: the step reports the shortfall and leaves the
    state as it was; replayed with the capacities grown by the shell's rule it equals a step that never
    lacked room."""
    from cusgs_jax.training import capacity

    monkeypatch.setattr(capacity, "PAIR_SLACK", 0)  # the fixed slack alone holds this tiny view's pairs
    cfg = _cfg()
    strategies, state, tx = _init(cfg)
    batch = _batch(3)
    before = _copy(state)
    tight = Capacities(visible_fraction=0.05, active_fraction=0.05, pairs_per_active=0.05)
    after, metrics = make_train_step(cfg, tx, strategies, tight)(_copy(state), batch)
    assert int(metrics["dropped_anchors"]) > 0
    for old, new in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(after)):
        np.testing.assert_array_equal(np.asarray(old), np.asarray(new))  # not even state.step moved
    grown, replays, kinds = tight, 0, set()
    while int(metrics["dropped_anchors"]) or int(metrics["dropped_gaussians"]) or int(metrics["dropped_pairs"]):
        kinds |= {k for k in ("dropped_anchors", "dropped_gaussians", "dropped_pairs") if int(metrics[k])}
        grown = grown.grown(jax.device_get(metrics), state.anchors.capacity, cfg.model.n_offsets)
        replayed, metrics = make_train_step(cfg, tx, strategies, grown)(_copy(state), batch)
        replays += 1
    assert kinds == {"dropped_anchors", "dropped_gaussians", "dropped_pairs"}  # every capacity ran out once
    assert replays <= 8 and int(replayed.step) == 1 and int(replayed.skipped) == 0
    roomy = Capacities(visible_fraction=1.0, active_fraction=1.0, pairs_per_active=50.0)
    reference, ref_metrics = make_train_step(cfg, tx, strategies, roomy)(_copy(state), batch)
    np.testing.assert_allclose(float(metrics["loss"]), float(ref_metrics["loss"]), rtol=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(replayed.anchors.params), jax.tree_util.tree_leaves(reference.anchors.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)


# --- B views per step, sharded over devices (make_batched_step) ------------------------------


def _views(seeds):
    """A B-view batch stacking ``_batch(seed)`` for each seed (leading view axis)."""
    singles = [_batch(s) for s in seeds]
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    return jax.tree_util.tree_map(stack, *singles), singles


def _batched(batch_size, devices, tx=None, **grow):
    cfg = _cfg(**grow).replace(train=dict(iterations=50, batch_size=batch_size, devices=devices))
    strategies, state, default_tx = _init(cfg)
    if tx is not None:
        state = state.replace(opt_state=tx.init(state.trainable))
    tx = tx or default_tx
    return cfg, strategies, state, tx, make_train_step(cfg, tx, strategies)


@pytest.mark.slow
def test_two_view_step_on_two_devices_equals_one_device(two_devices):
    """The same B = 2 step, views sharded over 2 devices or both on 1: same loss, same parameters.

    Tolerance: float32 reduction order (the two per-view gradient sums meet in a different order
    inside XLA's partitioned program): 1e-5 relative on the loss, 2e-6 absolute on parameters of
    size ~1 after 3 steps (measured ~4e-7).
    """
    finals = {}
    for devices in ("1", "2"):
        cfg, strategies, state, tx, step = _batched(2, devices)
        assert step.mesh.size == int(devices)
        for i in range(3):
            state, metrics = step(state, _views([2 * i, 2 * i + 1])[0])
        finals[devices] = jax.device_get((state.trainable, state.densify, float(metrics["loss"])))
    one, two = finals["1"], finals["2"]
    np.testing.assert_allclose(two[2], one[2], rtol=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(one[:2]), jax.tree_util.tree_leaves(two[:2])):
        np.testing.assert_allclose(np.asarray(b, np.float64), np.asarray(a, np.float64), atol=2e-6, rtol=1e-5)


@pytest.mark.slow
def test_batched_step_is_the_mean_of_its_views_and_counts_every_view(two_devices):
    """B = 2 from one state: loss = mean of the single-view losses, update (plain SGD, lr 1) = mean of
    the single-view updates, every additive densification statistic = the sum of both views' additions."""
    import optax

    sgd = optax.sgd(1.0)
    cfg1, strategies1, state1, _, single = _batched(1, "auto", tx=sgd)
    _, _, state2, _, batched = _batched(2, "2", tx=sgd)
    batch, singles = _views([3, 4])
    after, metrics = batched(_copy(state2), batch)
    runs = [single(_copy(state1), b) for b in singles]
    np.testing.assert_allclose(float(metrics["loss"]), np.mean([float(m["loss"]) for _, m in runs]), rtol=1e-5)
    before = jax.device_get(state1.trainable)
    delta = lambda s: jax.tree_util.tree_map(lambda a, b: np.asarray(a, np.float64) - b, s, before)  # noqa: E731
    expected = jax.tree_util.tree_map(lambda a, b: (a + b) / 2, *(delta(jax.device_get(s.trainable)) for s, _ in runs))
    for got, want in zip(jax.tree_util.tree_leaves(delta(jax.device_get(after.trainable))),
                         jax.tree_util.tree_leaves(expected)):
        np.testing.assert_allclose(got, want, atol=2e-6)
    stats0 = jax.device_get(state1.densify)
    added = [jax.tree_util.tree_map(lambda a, b: np.asarray(a, np.float64) - b, jax.device_get(s.densify), stats0)
             for s, _ in runs]
    got = jax.tree_util.tree_map(lambda a, b: np.asarray(a, np.float64) - b, jax.device_get(after.densify), stats0)
    leaves = jax.tree_util.tree_leaves(got)
    assert sum(float(np.abs(x).sum()) for x in leaves) > 0  # statistics were collected
    for g, a, b in zip(leaves, *(jax.tree_util.tree_leaves(x) for x in added)):
        np.testing.assert_allclose(g, a + b, rtol=1e-5, atol=1e-6)
    assert int(after.step) == 1 and int(after.skipped) == 0


@pytest.mark.slow
def test_sharded_step_compiles_once_across_growing_and_pruning(two_devices, compiles):
    cfg, strategies, state, tx, step = _batched(2, "2", grad_threshold=0.0, min_opacity=0.2, success_threshold=0.8)
    scaffold = _scaffold(strategies)
    grown = pruned = 0
    for i in range(10):
        state, metrics = step(state, _views([2 * i, 2 * i + 1])[0])
        if scaffold.due(i + 1):
            state, info = scaffold.update(state, tx, i + 1)
            assert not info.capacity_changed
            grown, pruned = grown + info.grown, pruned + info.pruned
    assert grown > 0 and pruned > 0  # the masks really changed between steps
    assert compiles.count("jit(train_step)") == 1
    assert int(state.step) == 10 and bool(metrics["finite"])


@pytest.mark.slow
def test_a_batched_step_whose_views_overflow_changes_nothing(two_devices):
    cfg, strategies, state, tx, step = _batched(2, "2")
    cfg = cfg.replace(model=dict(visible_fraction=1 / 64))  # far fewer visible slots than either view needs
    step = make_train_step(cfg, tx, strategies)
    before = jax.device_get(state)
    after, metrics = step(_copy(state), _views([0, 1])[0])
    assert int(metrics["dropped_anchors"]) > 0
    for a, b in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(jax.device_get(after))):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_a_valid_pixel_mask_makes_the_invalid_target_pixels_irrelevant(setup):
    """batch["valid"] (data.undistort=mask): the step's loss, metrics and new parameters do not depend
    on the target outside the mask, and do depend on it without one."""
    cfg, tx, strategies, step, state0 = setup
    valid = np.ones((H, W), bool)
    valid[:6] = False
    valid[:, :5] = False
    base = _batch(1)
    other = np.asarray(base["image"]).copy()
    other[~valid] = np.random.default_rng(5).uniform(size=(int((~valid).sum()), 3))
    results = []
    for image, mask in ((base["image"], valid), (other, valid), (other, None)):
        batch = dict(base, image=jnp.asarray(image))
        if mask is not None:
            batch["valid"] = jnp.asarray(mask)
        state, metrics = step(_copy(state0), batch)
        results.append((jax.device_get(state.trainable), {k: float(metrics[k]) for k in ("loss", "psnr")}))
    assert results[0][1] == results[1][1]
    for a, b in zip(jax.tree_util.tree_leaves(results[0][0]), jax.tree_util.tree_leaves(results[1][0])):
        np.testing.assert_array_equal(a, b)
    assert results[2][1]["loss"] != results[1][1]["loss"]


@pytest.mark.slow
def test_a_camera_with_a_lens_renders_through_it_and_a_zero_lens_is_the_pinhole(setup):
    """data.undistort=lens: a lens with zero coefficients (and a box around the whole view) gives the
    pinhole step's loss and update up to float rounding; a real lens changes them."""
    from cusgs_jax.splat.lens import Lens

    cfg, tx, strategies, step, state0 = setup
    base = _batch(2)
    box = jnp.asarray([-50.0, 50.0, -50.0, 50.0])
    results = []
    for lens in (None, Lens(jnp.zeros(6), box), Lens(jnp.asarray([0.2, 0.05, 0, 0, 0.01, 0.0]), box)):
        camera = dataclasses.replace(base["camera"], lens=lens)
        state, metrics = step(_copy(state0), dict(base, camera=camera))
        results.append((jax.device_get(state.trainable), float(metrics["loss"])))
    assert abs(results[1][1] - results[0][1]) < 1e-5 * abs(results[0][1])
    for a, b in zip(jax.tree_util.tree_leaves(results[0][0]), jax.tree_util.tree_leaves(results[1][0])):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert abs(results[2][1] - results[0][1]) > 1e-3 * abs(results[0][1])


@pytest.mark.slow
def test_the_pallas_compositor_takes_the_same_step(setup):
    """splat.backend=pallas (the kernels; Pallas's interpreter on a CPU) takes the step the JAX compositor
    takes: loss, metrics and new parameters agree to float32 rounding."""
    cfg, tx, strategies, step, state0 = setup
    pallas_step = make_train_step(cfg.replace(splat=dict(backend="pallas")), tx, strategies)
    theirs, ours = step(_copy(state0), _batch(2)), pallas_step(_copy(state0), _batch(2))
    assert float(theirs[1]["loss"]) == pytest.approx(float(ours[1]["loss"]), rel=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(theirs[0].trainable), jax.tree_util.tree_leaves(ours[0].trainable)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_step_settings_are_what_every_batch_carries(tiny_scene):
    """``step_settings`` is the one source of the settings a batch carries: ``make_batches`` gives them, value for
    value (loss weights, the seed's key, the learning rates of the scene's extent)."""
    from cusgs_jax.testing.runs import tiny_config
    from cusgs_jax.training.inputs import load_data, make_batches
    cfg = tiny_config(tiny_scene, "loss.l1_weight=0.7", "train.seed=3")
    scene, _ = load_data(cfg)
    batch = make_batches(scene, scene.train_indices, cfg, {}, None)(0)
    settings = step_settings(cfg, scene.extent)
    assert set(settings) == {"loss_weights", "seed_key", "learning_rates"}
    for key, value in settings.items():
        for a, b in zip(jax.tree_util.tree_leaves(batch[key]), jax.tree_util.tree_leaves(value), strict=True):
            np.testing.assert_array_equal(a, b)
    assert float(settings["loss_weights"]["l1"]) == np.float32(0.7)


def test_queries_composited_only_where_the_feature_loss_reads_take_the_dense_step(monkeypatch):
    """``features.sparse_queries`` composites the queries at the pixels the feature loss can read (each map's
    pixel centres) only: the step's loss and update are those of compositing them everywhere (to rounding)."""
    from cusgs_jax.config import FeatureModelConfig
    from cusgs_jax.splat.render import SparseChannels
    from cusgs_jax.model.field import read_pixels
    from cusgs_jax.testing.scenes import random_banks

    models = (FeatureModelConfig("a", query_dim=4), FeatureModelConfig("b", query_dim=6))
    banks = {name: jnp.asarray(b) for name, b in random_banks({"a": (5, 3), "b": (7, 2)}).items()}
    rng = np.random.default_rng(4)
    maps = {"a": (6, 8, 3), "b": (4, 5, 2)}  # coarser than the 24×32 image, as a stride-4/6 tap
    batch = dict(_batch(1), banks=banks,
                 features={name: jnp.asarray(rng.normal(size=shape).astype(np.float32)) for name, shape in maps.items()})
    pixels = read_pixels({name: shape[:2] for name, shape in maps.items()}, (H, W))
    assert pixels is not None and len(pixels) <= 6 * 8 + 4 * 5
    listed = []
    slots = SparseChannels.slots
    monkeypatch.setattr(SparseChannels, "slots", lambda self, grid: listed.append(self) or slots(self, grid))
    results = {}
    for sparse in (False, True):
        cfg = _cfg().replace(features=dict(models=models, hidden=8, sparse_queries=sparse, sample_pixels=0))
        strategies = make_strategies(cfg)
        state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies, banks)
        step = make_train_step(cfg, tx, strategies)
        state, metrics = step(state, batch)
        state, metrics = step(state, batch)  # a second step: the first update moved the queries' heads
        results[sparse] = jax.device_get((state.trainable, metrics["loss"]))
        assert bool(listed) == sparse and all(x == SparseChannels(10, pixels) for x in listed)
    np.testing.assert_allclose(results[True][1], results[False][1], rtol=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(results[True][0]), jax.tree_util.tree_leaves(results[False][0])):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_read_pixels_are_the_image_pixels_the_feature_loss_samples():
    from cusgs_jax.model.field import image_pixel_of, read_pixels

    pixels = read_pixels({"a": (30, 40), "b": (12, 16)}, (120, 160))
    rows, cols = image_pixel_of(np.arange(30)[:, None].repeat(40, 1).ravel(), np.tile(np.arange(40), 30),
                                (30, 40), (120, 160))
    assert set(np.asarray(rows) * 160 + np.asarray(cols)) <= set(pixels)
    assert len(pixels) == len(set(pixels)) <= 30 * 40 + 12 * 16
    assert read_pixels({"full": (120, 160)}, (120, 160)) is None  # a full-resolution map: every pixel
    assert read_pixels({"full": (120, 160), "coarse": (30, 40)}, (120, 160)) is None  # one map that reads all
    assert len(read_pixels({"half": (60, 80)}, (120, 160))) == 60 * 80  # a quarter of the pixels: sparse
