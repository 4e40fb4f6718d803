"""Feature-aware pruning: scores against NumPy, masking, selection, jit, a rendered scene, the strategy."""

from __future__ import annotations

import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import PruneConfig
from cusgs_jax.densify.base import ViewRecord
from cusgs_jax.densify.feature_prune import (FeaturePruneStrategy, PruneDials, PruneStats, _floor_ratio, kth_smallest,
                                             accumulate_prune_stats, anchor_scores, gaussian_volume_weight,
                                             prune_due, prune_pass, select_prune, stats_window)
from cusgs_jax.densify.scaffold import GrowStats
from cusgs_jax.model.anchors import AnchorParams, AnchorState
from cusgs_jax.model.decode import VisibleSlots
from cusgs_jax.splat import rasterize
from cusgs_jax.testing.prune_reference import significance_reference
from cusgs_jax.training.state import TrainState


def _anchors(centers, alive, latent) -> AnchorState:
    """Anchors with the given centres, alive mask and latents z (offsets and scales are not read)."""
    a = latent.shape[0]
    params = AnchorParams(offsets=jnp.zeros((a, 1, 3)), log_scaling=jnp.zeros((a, 6)), latent=jnp.asarray(latent))
    return AnchorState(jnp.asarray(centers), jnp.asarray(alive), params)


def _random_view(rng, capacity, num_slots, n, f, alive, *, pad=0):
    """A view in decode_view's gathered layout: unique alive slots, then ``pad`` invalid entries."""
    slots = rng.choice(np.nonzero(alive)[0], num_slots, replace=False)
    slots = np.concatenate([slots, np.zeros(pad, np.int64)]).astype(np.int32)
    valid = np.arange(num_slots + pad) < num_slots
    g = (num_slots + pad) * n
    return dict(
        slots=slots, valid=valid,
        latent_grad=rng.normal(size=(num_slots + pad, f)).astype(np.float32) * 0.1,
        significance=rng.uniform(0, 50, g).astype(np.float32),
        scales=np.exp(rng.uniform(-4, -1, (g, 3))).astype(np.float32),
        active=rng.uniform(size=g) < 0.8,
    )


def _accumulate(stats, view, enabled=True, cfg=None):
    cfg = cfg or PruneConfig()
    return accumulate_prune_stats(stats, jnp.asarray(view["slots"]), jnp.asarray(view["valid"]),
                                  jnp.asarray(view["latent_grad"]), jnp.asarray(view["significance"]),
                                  jnp.asarray(view["scales"]), jnp.asarray(view["active"]),
                                  jnp.asarray(enabled), cfg)


def test_anchor_scores_match_numpy():
    rng = np.random.default_rng(0)
    a, f = 40, 8
    cfg = PruneConfig()
    alive = rng.uniform(size=a) < 0.8
    latent = rng.normal(size=(a, f)).astype(np.float32)
    count = rng.integers(0, 5, a).astype(np.float32)
    grad_sum = (rng.uniform(0, 0.1, a) * count).astype(np.float32)
    contrib = (rng.uniform(0, 1e4, a) * (count > 0)).astype(np.float32)
    stats = PruneStats(jnp.asarray(grad_sum), jnp.asarray(count), jnp.asarray(contrib))
    got = np.asarray(anchor_scores(jnp.asarray(latent), stats, jnp.asarray(alive), cfg))

    g = np.where(count > 0, grad_sum.astype(np.float64) / np.maximum(count, 1), 0.0)
    mean = contrib[alive].astype(np.float64).mean()
    want = 2.0 * np.linalg.norm(latent.astype(np.float64), axis=-1) + 8.0 * g + contrib / mean
    want = np.where(alive, want, np.inf)
    np.testing.assert_array_equal(np.isinf(got), ~alive)
    np.testing.assert_allclose(got[alive], want[alive], rtol=1e-5)
    # contributions of dead slots do not enter the normalisation
    junk = PruneStats(stats.latent_grad_norm, stats.grad_count,
                      jnp.where(jnp.asarray(alive), stats.contrib, 1e9))
    np.testing.assert_array_equal(anchor_scores(jnp.asarray(latent), junk, jnp.asarray(alive), cfg), got)
    # nothing accumulated: the contribution term is 0, not NaN
    empty = anchor_scores(jnp.asarray(latent), PruneStats.zeros(a), jnp.asarray(alive), cfg)
    np.testing.assert_allclose(np.asarray(empty)[alive], 2.0 * np.linalg.norm(latent, axis=-1)[alive], rtol=1e-6)


def test_accumulate_and_score_match_reference(compiles):
    rng = np.random.default_rng(1)
    a, n, f = 30, 4, 6
    cfg = PruneConfig(min_visits=0)
    alive = np.ones(a, bool)
    alive[[3, 17, 25]] = False
    latent = rng.normal(size=(a, f)).astype(np.float32)
    views = [_random_view(rng, a, 12, n, f, alive, pad=3) for _ in range(5)]
    views[2]["enabled"] = False
    stats = PruneStats.zeros(a)
    def accumulate(s, v, e):
        return accumulate_prune_stats(s, v["slots"], v["valid"], v["latent_grad"], v["significance"], v["scales"],
                                      v["active"], e, cfg)

    step = jax.jit(accumulate)
    for view in views:
        arrays = {k: jnp.asarray(v) for k, v in view.items() if k != "enabled"}
        stats = step(stats, arrays, jnp.asarray(view.get("enabled", True)))
    assert compiles.count("jit(accumulate)") == 1  # one program for the five views
    got = np.asarray(anchor_scores(jnp.asarray(latent), stats, jnp.asarray(alive), cfg))
    want = significance_reference(latent, alive, views, cfg)
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[alive], want[alive], rtol=2e-5)


def test_masked_entries_add_exactly_zero():
    rng = np.random.default_rng(2)
    a, n, f = 25, 3, 5
    alive = np.ones(a, bool)
    base = _random_view(rng, a, 10, n, f, alive)
    base["active"][[0, 7]] = False
    start = PruneStats(*(jnp.asarray(rng.uniform(0, 5, a).astype(np.float32)) for _ in range(3)))
    ref = _accumulate(start, base)

    # inactive Gaussians with garbage significance / huge volumes change nothing
    noisy = {k: np.array(v) for k, v in base.items()}
    noisy["significance"][[0, 7]] = [np.nan, 1e30]
    noisy["scales"][[0, 7]] = 1e6
    got = _accumulate(start, noisy)
    for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_array_equal(x, y)

    # padded (invalid) entries that repeat slot 0 with garbage everywhere change nothing
    padded = {k: np.array(v) for k, v in base.items()}
    padded["slots"] = np.concatenate([base["slots"], [0, 0]]).astype(np.int32)
    padded["valid"] = np.concatenate([base["valid"], [False, False]])
    padded["latent_grad"] = np.concatenate([base["latent_grad"], np.full((2, f), np.nan, np.float32)])
    padded["significance"] = np.concatenate([base["significance"], np.full(2 * n, 1e9, np.float32)])
    padded["scales"] = np.concatenate([base["scales"], np.full((2 * n, 3), 1e3, np.float32)])
    padded["active"] = np.concatenate([base["active"], np.ones(2 * n, bool)])
    got = _accumulate(start, padded)
    for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_array_equal(x, y)

    # a disabled call adds nothing, even with NaN inputs
    bad = {k: np.array(v) for k, v in base.items()}
    bad["latent_grad"][:] = np.nan
    bad["significance"][:] = np.nan
    off = _accumulate(start, bad, enabled=False)
    for x, y in zip(jax.tree_util.tree_leaves(off), jax.tree_util.tree_leaves(start)):
        np.testing.assert_array_equal(x, y)

    # the slots that were not decoded are untouched, the decoded ones counted once
    touched = np.zeros(a, bool)
    touched[base["slots"]] = True
    np.testing.assert_array_equal(ref.grad_count, start.grad_count + jnp.asarray(touched, jnp.float32))
    np.testing.assert_array_equal(np.asarray(ref.contrib)[~touched], np.asarray(start.contrib)[~touched])


def test_volume_weight_matches_lightgaussian():
    cfg = PruneConfig()
    # volumes 1..10 as (v, 1, 1); decreasing order index int(0.9·10) = 9 → V_ref = 1
    vol = np.arange(1.0, 11.0)
    scales = np.stack([vol, np.ones(10), np.ones(10)], -1)
    w = gaussian_volume_weight(jnp.asarray(scales, jnp.float32), jnp.ones(10, bool), cfg)
    np.testing.assert_allclose(w, vol ** 0.1, rtol=1e-6)

    # a hand example with 20 Gaussians, two inactive giants (ignored) and a 2x2x2 cube
    rng = np.random.default_rng(3)
    scales = np.exp(rng.uniform(-3, 0, (20, 3)))
    scales[4] = 2.0
    active = np.ones(20, bool)
    active[[5, 11]] = False
    scales[[5, 11]] = 100.0
    w = np.asarray(gaussian_volume_weight(jnp.asarray(scales, jnp.float32), jnp.asarray(active), cfg))

    # LightGaussian calculate_v_imp_score, transcribed, on the active Gaussians
    volume = np.prod(scales[active], axis=1)
    kth_percent_largest = np.sort(volume)[::-1][int(len(volume) * 0.9)]  # 18 actives → index 16
    want = np.zeros(20)
    want[active] = np.power(volume / kth_percent_largest, 0.1)
    np.testing.assert_allclose(w, want, rtol=1e-5)
    assert w[5] == 0 and w[11] == 0
    np.testing.assert_allclose(w[4], (8.0 / kth_percent_largest) ** 0.1, rtol=1e-5)
    # V_ref is a small volume: most weights exceed 1
    assert (w[active] >= 1.0 - 1e-6).sum() == int(len(volume) * 0.9) + 1
    # no active Gaussian at all → all zero, finite
    none = gaussian_volume_weight(jnp.asarray(scales, jnp.float32), jnp.zeros(20, bool), cfg)
    np.testing.assert_array_equal(none, np.zeros(20))


@pytest.mark.parametrize("case", ["random", "ties_zeros_inf", "negative_and_nan", "one"])
def test_kth_smallest_equals_the_sorted_entry(case):
    rng = np.random.default_rng(3)
    if case == "random":
        values = rng.lognormal(-9.0, 3.0, 5000)
    elif case == "ties_zeros_inf":
        values = np.concatenate([rng.choice([0.0, 1e-30, 2.5, 2.5, np.inf], 300), rng.random(200)])
    elif case == "negative_and_nan":
        values = np.concatenate([rng.normal(size=400) * 1e3, [np.nan, -0.0, 0.0, -np.inf, np.inf]])
    else:
        values = np.array([7.0])
    values = values.astype(np.float32)
    kth = jax.jit(kth_smallest)
    ascending = np.sort(values)  # NumPy also sorts NaN last
    ks = sorted({0, len(values) - 1, *rng.integers(0, len(values), 40).tolist()})
    got = np.array([float(kth(jnp.asarray(values), jnp.int32(k))) for k in ks])
    np.testing.assert_array_equal(got, ascending[ks])


def test_floor_ratio_is_exact():
    counts = jnp.arange(0, 200_001, dtype=jnp.int32)
    for ratio, (p, q) in ((0.001, (1, 1000)), (0.01, (1, 100)), (0.9, (9, 10)), (0.0015, (3, 2000))):
        np.testing.assert_array_equal(_floor_ratio(counts, ratio), np.arange(200_001) * p // q)


def test_select_prune_ratio_order_ties_and_dead(compiles):
    rng = np.random.default_rng(4)
    a = 1200
    alive = np.zeros(a, bool)
    alive[rng.choice(a, 1000, replace=False)] = True
    scores = rng.uniform(0, 10, a).astype(np.float32)
    scores[~alive] = -100.0  # dead slots with the lowest scores are still never chosen
    def select_one_percent(s, al):
        return select_prune(s, al, 0.01)

    select = jax.jit(select_one_percent)
    chosen = np.asarray(select(jnp.asarray(scores), jnp.asarray(alive)))
    assert chosen.sum() == 10
    assert not (chosen & ~alive).any()
    lowest = np.nonzero(alive)[0][np.argsort(scores[alive], kind="stable")[:10]]
    np.testing.assert_array_equal(np.nonzero(chosen)[0], np.sort(lowest))

    # ties: equal scores → the lowest alive indices
    flat = np.ones(a, np.float32)
    chosen = np.asarray(select(jnp.asarray(flat), jnp.asarray(alive)))
    np.testing.assert_array_equal(np.nonzero(chosen)[0], np.nonzero(alive)[0][:10])
    # a partial tie at the cut: two anchors share the 10th-lowest score, the lower index wins
    tie = np.asarray(scores).copy()
    idx = np.nonzero(alive)[0]
    order = idx[np.argsort(scores[idx], kind="stable")]
    tie[order[10]] = tie[order[9]]
    first, second = sorted([order[9], order[10]])
    chosen = np.asarray(select(jnp.asarray(tie), jnp.asarray(alive)))
    assert chosen[first] and not chosen[second] and chosen.sum() == 10
    assert compiles.count("jit(select_one_percent)") == 1

    # floor: 999 alive at 0.1 % → 0; 1000 → 1; never negative
    for count, want in ((999, 0), (1000, 1), (0, 0)):
        al = np.zeros(a, bool)
        al[:count] = True
        assert int(select_prune(jnp.asarray(scores), jnp.asarray(al), 0.001).sum()) == want
    # eligibility caps the number chosen
    eligible = np.zeros(a, bool)
    eligible[np.nonzero(alive)[0][:4]] = True
    chosen = np.asarray(select_prune(jnp.asarray(scores), jnp.asarray(alive), 0.01, jnp.asarray(eligible)))
    np.testing.assert_array_equal(chosen, eligible & alive)


def test_prune_pass_jit_once_and_clears_alive(compiles):
    rng = np.random.default_rng(5)
    a, f = 500, 8
    cfg = PruneConfig(ratio=0.01)
    centers = jnp.asarray(rng.normal(size=(a, 3)), jnp.float32)
    latent = jnp.asarray(rng.normal(size=(a, f)), jnp.float32)
    stats = PruneStats(jnp.asarray(rng.uniform(0, 1, a), jnp.float32), jnp.full(a, 3.0),
                       jnp.asarray(rng.uniform(0, 100, a), jnp.float32))
    def one_pass(anchors, s):
        return prune_pass(anchors, s, cfg)

    run = jax.jit(one_pass)
    for count in (500, 420, 137):
        alive = np.zeros(a, bool)
        alive[rng.choice(a, count, replace=False)] = True
        anchors = _anchors(centers, jnp.asarray(alive), latent)
        new, fresh, info = run(anchors, stats)
        new_alive = np.asarray(new.alive)
        pruned = alive & ~new_alive
        assert int(info["pruned"]) == pruned.sum() == math.floor(count * 0.01)
        assert int(info["alive"]) == new_alive.sum() and not (new_alive & ~alive).any()
        scores = np.asarray(anchor_scores(latent, stats, jnp.asarray(alive), cfg))
        if pruned.any():  # the pruned ones are the lowest-scoring alive anchors
            assert scores[pruned].max() <= scores[alive & ~pruned].min()
        for leaf in jax.tree_util.tree_leaves(fresh):
            np.testing.assert_array_equal(leaf, np.zeros(a))
    assert compiles.count("jit(one_pass)") == 1

    # anchors not decoded since the last pass are kept (min_visits = 1)
    unseen = PruneStats(stats.latent_grad_norm, stats.grad_count.at[:250].set(0.0), stats.contrib)
    new, _, info = run(_anchors(centers, jnp.ones(a, bool), latent), unseen)
    assert int(info["candidates"]) == 250 and int(info["pruned"]) == 5
    assert np.asarray(new.alive)[:250].all()

    # "none" and "scaffold" change no anchor
    for strategy in ("none", "scaffold"):
        anchors = _anchors(centers, jnp.ones(a, bool), latent)
        off = PruneConfig(strategy=strategy)
        new, fresh, info = jax.jit(lambda an, s, c=off: prune_pass(an, s, c))(anchors, stats)
        np.testing.assert_array_equal(new.alive, anchors.alive)
        assert int(info["pruned"]) == 0
    with pytest.raises(ValueError):
        PruneConfig(strategy="lightgaussian")


@pytest.mark.parametrize("ratio", [0.001, 0.01, 0.0015, 1 / 3, 0.9, 0.0])
def test_a_pass_with_traced_dials_equals_the_pass_with_constants(ratio):
    """The strategy passes ratio, weights and min_visits as arguments: the same anchors pruned, the same
    scores, as with the configuration's constants (a non-decimal ratio such as 1/3 takes the float path)."""
    rng = np.random.default_rng(11)
    a, f = 700, 8
    for lambda_norm, lambda_grad, min_visits in ((2.0, 8.0, 1), (0.37, 1.9, 0), (6.0, 4.0, 3)):
        cfg = PruneConfig(ratio=ratio, lambda_norm=lambda_norm, lambda_grad=lambda_grad, min_visits=min_visits)
        alive = rng.uniform(size=a) < 0.8
        anchors = _anchors(jnp.asarray(rng.normal(size=(a, 3)), jnp.float32), jnp.asarray(alive),
                           jnp.asarray(rng.normal(size=(a, f)), jnp.float32))
        stats = PruneStats(jnp.asarray(rng.uniform(0, 1, a), jnp.float32),
                           jnp.asarray(rng.integers(0, 5, a), jnp.float32), jnp.asarray(rng.uniform(0, 100, a), jnp.float32))
        constant = jax.jit(lambda an, st, c=cfg: prune_pass(an, st, c))(anchors, stats)
        traced = jax.jit(lambda an, st, d, c=cfg: prune_pass(an, st, c, d))(anchors, stats, PruneDials.of(cfg))
        np.testing.assert_array_equal(traced[0].alive, constant[0].alive)
        assert {k: int(v) for k, v in traced[2].items()} == {k: int(v) for k, v in constant[2].items()}
        assert int(traced[2]["pruned"]) == min(int(_floor_ratio(jnp.int32(alive.sum()), ratio)),
                                               int(traced[2]["candidates"]))
        np.testing.assert_array_equal(anchor_scores(anchors.params.latent, stats, anchors.alive, PruneDials.of(cfg)),
                                      anchor_scores(anchors.params.latent, stats, anchors.alive, cfg))


def test_a_sweep_over_ratio_and_weights_lowers_one_pruning_program():
    """Jobs that differ in prune.ratio, λ_n, λ_g or min_visits lower the same pass (one persistent-cache entry);
    another strategy or schedule is the only thing that changes the program."""
    a, f = 300, 8
    anchors = _anchors(jnp.zeros((a, 3)), jnp.ones(a, bool), jnp.zeros((a, f)))
    stats = PruneStats.zeros(a)

    def lowered(cfg):
        strategy = FeaturePruneStrategy(cfg)
        return strategy._pass.lower(anchors, stats, strategy.dials).as_text()

    base = lowered(PruneConfig())
    for changed in (dict(ratio=0.01), dict(ratio=1 / 3), dict(lambda_norm=8.0, lambda_grad=2.0), dict(min_visits=4),
                    dict(start=200, interval=50)):
        assert lowered(PruneConfig(**changed)) == base, changed


def test_schedule():
    cfg = PruneConfig()
    assert [s for s in range(0, 16001, 50) if prune_due(s, cfg)] == list(range(500, 15001, 100))
    assert not stats_window(399, cfg) and stats_window(400, cfg) and stats_window(14999, cfg)
    assert not stats_window(15000, cfg)
    traced = jax.jit(lambda s: (prune_due(s, cfg), stats_window(s, cfg)))
    assert [bool(x) for x in traced(jnp.int32(600))] == [True, True]
    assert not prune_due(600, PruneConfig(strategy="none"))


def test_hidden_anchor_has_no_contribution_on_a_render():
    """Render 5 anchors × 3 Gaussians; the anchor behind an opaque wall gets contribution ~0 and is pruned."""
    n, width, height, focal = 3, 40, 28, 36.0
    rng = np.random.default_rng(6)

    def group(z, scale, opacity, spread):
        xy = rng.uniform(-spread, spread, (n, 2)) * z
        return np.concatenate([xy, np.full((n, 1), z)], -1), np.full((n, 3), scale), np.full(n, opacity)

    # gathered order: entry j → slot; slot roles
    slots = np.array([2, 0, 4, 1, 0], np.int32)  # the last entry is padding
    valid = np.array([True, True, True, True, False])
    parts = [
        group(3.0, 20.0, 1.0, 0.0),   # slot 2: opaque wall covering the image
        group(6.0, 0.2, 0.8, 0.2),    # slot 0: hidden behind the wall
        group(1.5, 0.05, 0.5, 0.3),   # slot 4: in front
        group(2.0, 0.1, 0.6, 0.3),    # slot 1: in front
        group(1.0, 0.1, 0.0, 0.3),    # padding: switched off
    ]
    means = np.concatenate([p[0] for p in parts]).astype(np.float32)
    scales = np.concatenate([p[1] for p in parts]).astype(np.float32)
    opacities = np.concatenate([p[2] for p in parts]).astype(np.float32)
    active = opacities > 0
    g = means.shape[0]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (g, 1)).astype(np.float32)
    colors = rng.uniform(0, 1, (g, 3)).astype(np.float32)
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], np.float32)
    out = rasterize(jnp.asarray(means), jnp.asarray(quats), jnp.asarray(scales), jnp.asarray(opacities),
                    jnp.asarray(colors), jnp.eye(4), jnp.asarray(K), width, height)
    assert int(out.overflow) == 0
    assert float(out.alpha.min()) > 0.99  # the wall really covers the image

    a, f = 6, 4
    alive = np.array([True, True, True, False, True, False])
    latent = np.zeros((a, f), np.float32)
    latent[:, 0] = 1.0  # equal latent norms: only the contribution decides
    latent_grad = np.tile(np.array([0.01, 0, 0, 0], np.float32), (len(slots), 1))
    cfg = PruneConfig(ratio=0.25)  # 4 alive → prune exactly 1
    stats = accumulate_prune_stats(PruneStats.zeros(a), jnp.asarray(slots), jnp.asarray(valid),
                                   jnp.asarray(latent_grad), out.significance, jnp.asarray(scales),
                                   jnp.asarray(active), jnp.asarray(True), cfg)
    contrib = np.asarray(stats.contrib)
    visible = contrib[[1, 2, 4]]
    assert visible.min() > 1.0
    assert contrib[0] <= 1e-6 * visible.min()
    assert contrib[3] == 0 and contrib[5] == 0
    scores = np.asarray(anchor_scores(jnp.asarray(latent), stats, jnp.asarray(alive), cfg))
    assert np.argmin(scores) == 0
    new, _, info = prune_pass(_anchors(jnp.zeros((a, 3)), jnp.asarray(alive), jnp.asarray(latent)), stats, cfg)
    assert int(info["pruned"]) == 1
    np.testing.assert_array_equal(new.alive, alive & (np.arange(a) != 0))


def test_strategy_accumulates_views_and_prunes_by_mask():
    """FeaturePruneStrategy: the step hook is accumulate_prune_stats on the view's record (inside the
    window, finite steps only); the pass clears alive bits and resets only its own statistics."""
    rng = np.random.default_rng(7)
    a, n, f = 40, 3, 5
    cfg = PruneConfig(ratio=0.1, start=200, interval=100, stop=1000)
    strategy = FeaturePruneStrategy(cfg)
    alive = np.ones(a, bool)
    alive[[2, 9]] = False
    view = _random_view(rng, a, 12, n, f, alive, pad=2)
    render = types.SimpleNamespace(significance=jnp.asarray(view["significance"]))
    gaussians = types.SimpleNamespace(scales=jnp.asarray(view["scales"]), active=jnp.asarray(view["active"]))

    def record(step, finite=True):
        slots = VisibleSlots(jnp.asarray(view["slots"]), jnp.asarray(view["valid"]), jnp.int32(0))
        return ViewRecord(slots=slots, gaussians=gaussians, render=render, grad2d=jnp.zeros((14 * n, 2)),
                          latent_grad=jnp.asarray(view["latent_grad"]), capacity=a, width=8, height=8,
                          step=jnp.int32(step), finite=jnp.asarray(finite))

    stats = strategy.accumulate(strategy.init_state(a), record(150))
    want = _accumulate(PruneStats.zeros(a), view, cfg=cfg)
    for x, y in zip(jax.tree_util.tree_leaves(stats), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(x, y)
    assert float(jnp.sum(stats.grad_count)) == 12
    for step, finite in ((99, True), (1000, True), (150, False)):  # outside the window / skipped update
        off = strategy.accumulate(strategy.init_state(a), record(step, finite))
        assert not any(np.any(np.asarray(x)) for x in jax.tree_util.tree_leaves(off)), (step, finite)
    assert [s for s in range(0, 1101, 50) if strategy.due(s)] == list(range(200, 1001, 100))

    latent = rng.normal(size=(a, f)).astype(np.float32)
    eligible = np.asarray(stats.grad_count) >= 1
    scores = np.asarray(anchor_scores(jnp.asarray(latent), stats, jnp.asarray(alive), cfg))
    expect = np.zeros(a, bool)  # floor(0.1 · 38) = 3 lowest-scoring decoded alive anchors
    expect[np.flatnonzero(alive & eligible)[np.argsort(scores[alive & eligible], kind="stable")[:3]]] = True
    grow = GrowStats(*(jnp.full(shape, 2.0) for shape in ((a, n), (a, n), (a,), (a,))))
    state = TrainState(anchors=_anchors(jnp.zeros((a, 3)), alive, latent), nets={}, opt_state=None,
                       densify={"feature_prune": stats, "scaffold": grow}, step=jnp.int32(0), skipped=jnp.int32(0))
    new, info = strategy.update(state, None, 200)
    assert info.pruned == 3 and info.extra["alive"] == 35
    np.testing.assert_array_equal(new.anchors.alive, alive & ~expect)
    np.testing.assert_array_equal(new.anchors.params.latent, latent)  # a mask flip: nothing else moves
    for x in jax.tree_util.tree_leaves(new.densify["feature_prune"]):
        np.testing.assert_array_equal(x, np.zeros(a))
    for x in jax.tree_util.tree_leaves(new.densify["scaffold"]):
        np.testing.assert_array_equal(x, 2.0)
