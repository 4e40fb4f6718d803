"""Work capacities (training/capacity.py): bucketed growth rules and what they are applied to."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.training import capacity


def test_visible_fraction_grows_in_buckets_to_hold_what_was_seen_and_stops_at_one():
    grown = capacity.grown_visible_fraction(0.1, needed_slots=300, capacity=1000)
    assert grown * 1000 >= capacity.GROWTH_HEADROOM * 300 and grown * capacity.FRACTION_BUCKET == int(grown * capacity.FRACTION_BUCKET)
    assert capacity.grown_visible_fraction(0.6, needed_slots=500, capacity=1000) == 0.75  # at least one bucket
    assert capacity.grown_visible_fraction(0.6, needed_slots=601, capacity=1000) == 0.875  # 1.25 × 601 = 751
    assert capacity.grown_visible_fraction(0.9, needed_slots=1000, capacity=1000) == 1.0
    # few distinct sizes: a run that keeps seeing slightly more grows in coarse steps
    sizes = {capacity.grown_visible_fraction(0.125, needed, 1000) for needed in range(130, 900, 7)}
    assert len(sizes) <= capacity.FRACTION_BUCKET


def test_pair_capacity_grows_by_half_steps_with_headroom():
    grown = capacity.grown_pairs_per_gaussian(3.0, needed_pairs=50_000, num_gaussians=10_000)
    assert capacity.max_pairs(grown, 10_000) >= 50_000 * 1.2
    assert grown >= 4.5 and (2 * grown) == int(2 * grown)
    assert capacity.grown_pairs_per_gaussian(3.0, needed_pairs=10, num_gaussians=10) == 4.5  # ≥ 1.5×


def test_active_fraction_grows_in_sixteenths_with_headroom_and_stops_at_one():
    grown = capacity.grown_active_fraction(0.25, needed=400, decoded=1000)
    assert grown * 1000 >= capacity.GROWTH_HEADROOM * 400 and grown * capacity.ACTIVE_BUCKET == int(grown * capacity.ACTIVE_BUCKET)
    assert capacity.grown_active_fraction(0.25, needed=200, decoded=1000) == 0.3125  # at least one bucket
    assert capacity.grown_active_fraction(0.9, needed=1000, decoded=1000) == 1.0


def test_capacities_give_static_sizes_that_follow_the_anchor_capacity():
    caps = capacity.Capacities(visible_fraction=0.5, active_fraction=0.25, pairs_per_active=4.0)
    assert caps.visible_slots(1000) == 500 and caps.active_gaussians(1000, 10) == 1250
    assert caps.pairs(1000, 10) == 4 * 1250 + capacity.PAIR_SLACK
    assert caps.visible_slots(2000) == 1000  # a grown anchor capacity keeps the fractions
    assert capacity.Capacities(1.0, 1.0, 1.0).active_gaussians(3, 2) == 6  # never more than S·N
    assert capacity.Capacities.from_config(Config()) == capacity.Capacities(
        Config().model.visible_fraction, Config().splat.active_fraction, Config().splat.max_pairs_per_gaussian)


def test_a_grown_anchor_capacity_widens_the_visible_slots_but_keeps_the_active_gaussians_and_pairs_it_had():
    caps = capacity.Capacities(visible_fraction=0.625, active_fraction=0.4375, pairs_per_active=4.0)
    grown = caps.regrown(10_404, 15_606, 10)  # the README main job's growth
    assert (grown.visible_fraction, grown.pairs_per_active) == (0.625, 4.0)
    assert grown.visible_slots(15_606) > caps.visible_slots(10_404)
    # G_act 28,451 of S·N = 97,540 decoded: 4.67 sixteenths -> 5/16 (30,482), not 7/16 (42,674) as before
    assert grown.active_fraction == 0.3125 and grown.active_gaussians(15_606, 10) == 30_482
    rng = np.random.default_rng(0)
    for _ in range(500):
        old = int(rng.integers(1, 50_000))
        new = old + int(rng.integers(1, 3 * old + 2))
        caps = capacity.Capacities(float(rng.integers(1, 9)) / 8, float(rng.integers(1, 17)) / 16, float(rng.integers(1, 20)) / 2)
        n = int(rng.integers(1, 12))
        grown = caps.regrown(old, new, n)
        held = caps.active_gaussians(old, n)
        assert grown.active_gaussians(new, n) >= held and grown.pairs(new, n) >= caps.pairs(old, n)
        assert grown.active_fraction <= caps.active_fraction and (grown.visible_fraction, grown.pairs_per_active) == (
            caps.visible_fraction, caps.pairs_per_active)
        assert grown.active_fraction * capacity.ACTIVE_BUCKET == int(grown.active_fraction * capacity.ACTIVE_BUCKET)
        tighter = dataclasses.replace(grown, active_fraction=grown.active_fraction - 1 / capacity.ACTIVE_BUCKET)
        assert tighter.active_fraction <= 0 or tighter.active_gaussians(new, n) < held  # the least sixteenth
    assert caps.regrown(2000, 1000, 10) == caps and caps.regrown(1000, 1000, 10) == caps  # only a growth


def test_capacities_grow_the_slots_first_then_the_active_gaussians_then_the_pairs():
    caps = capacity.Capacities(visible_fraction=0.25, active_fraction=0.25, pairs_per_active=3.0)
    everything = dict(visible_anchors=250, dropped_anchors=100, active_gaussians=600, dropped_gaussians=70,
                      pairs=900, dropped_pairs=50)
    grown = caps.grown(everything, anchor_capacity=1000, n_offsets=10)
    assert grown.visible_fraction > 0.25 and (grown.active_fraction, grown.pairs_per_active) == (0.25, 3.0)
    active = dict(everything, dropped_anchors=0)
    grown = caps.grown(active, anchor_capacity=1000, n_offsets=10)  # S·N = 2500, G_act = 625 < 670 needed
    assert grown.active_fraction > 0.25 and (grown.visible_fraction, grown.pairs_per_active) == (0.25, 3.0)
    assert grown.active_gaussians(1000, 10) >= 670
    pairs_only = dict(active, dropped_gaussians=0, pairs=9000, dropped_pairs=5000)
    grown = caps.grown(pairs_only, anchor_capacity=1000, n_offsets=10)
    assert grown.pairs_per_active > 3.0 and grown.pairs(1000, 10) >= 14_000
    assert caps.grown(dict(visible_anchors=3, dropped_anchors=0, active_gaussians=4, dropped_gaussians=0,
                           pairs=1, dropped_pairs=0), 10, 4) == caps


def test_saved_capacities_are_restored_but_never_shrink_the_first_ones():
    first = capacity.Capacities.from_config(Config())
    grown = capacity.Capacities(visible_fraction=0.875, active_fraction=0.5, pairs_per_active=9.0)
    assert first.restored(grown.as_dict()) == grown
    bigger = capacity.Capacities(1.0, 1.0, 20.0)
    assert bigger.restored(grown.as_dict()) == bigger
    assert first.restored(None) == first
    # metadata written before compaction (pairs per decoded Gaussian) restores the slots only
    old = first.restored({"visible_fraction": 0.875, "max_pairs_per_gaussian": 4.5})
    assert old == capacity.Capacities(0.875, first.active_fraction, first.pairs_per_active)
    with pytest.raises(KeyError):
        first.restored({"max_pairs_per_gaussian": 1.0})


def test_evaluation_capacities_give_the_visible_slots_headroom_in_buckets():
    Capacities = capacity.Capacities
    caps = Capacities(visible_fraction=0.375, active_fraction=0.4375, pairs_per_active=2.5)
    evaluation = caps.for_evaluation()
    assert evaluation.visible_fraction == 0.625  # 1.5 × 0.375 = 0.5625, rounded up to eighths
    assert (evaluation.active_fraction, evaluation.pairs_per_active) == (0.4375, 2.5)
    assert evaluation.visible_slots(10_000) >= 1.5 * caps.visible_slots(10_000)
    assert evaluation.active_gaussians(10_000, 10) >= 1.5 * caps.active_gaussians(10_000, 10)
    assert Capacities(0.875, 0.5, 2.0).for_evaluation().visible_fraction == 1.0  # never beyond every slot


def test_shortfall_reports_what_a_step_would_and_replayed_follows_the_replays_in_order():
    caps = capacity.Capacities(visible_fraction=0.375, active_fraction=0.4375, pairs_per_active=4.0)
    A, N = 10404, 10
    slots, active, pairs = caps.visible_slots(A), caps.active_gaussians(A, N), caps.pairs(A, N)
    fits = dict(visible_anchors=slots, active_gaussians=active, pairs=pairs)
    assert caps.shortfall(fits, A, N) is None and caps.replayed([fits], A, N) == []
    over = dict(fits, visible_anchors=slots + 628)
    short = caps.shortfall(over, A, N)
    assert short == dict(visible_anchors=slots, dropped_anchors=628)
    assert caps.grown(short, A, N) == caps.grown(dict(visible_anchors=slots, dropped_anchors=628), A, N)
    # a run meeting these views in order: slots grow for the first, pairs for the third, nothing for the second
    views = [over, fits, dict(fits, pairs=3 * pairs)]
    passed = caps.replayed(views, A, N)
    first = caps.grown(short, A, N)
    assert passed[0] == first and first.visible_fraction == 0.625  # the main job's replay after step 400
    assert len(passed) == 2 and passed[1].pairs_per_active > first.pairs_per_active
    assert passed[1].shortfall(views[2], A, N) is None


def test_roomy_means_every_view_fits_each_capacity_with_a_growths_headroom():
    caps = capacity.Capacities(visible_fraction=0.5, active_fraction=0.5, pairs_per_active=4.0)
    A, N = 1024, 10
    slots, active, pairs = caps.visible_slots(A), caps.active_gaussians(A, N), caps.pairs(A, N)
    room = dict(visible_anchors=int(slots / 1.25), active_gaussians=int(active / 1.25), pairs=int(pairs / 1.25))
    assert caps.roomy([room, room], A, N)
    for key in room:  # any one need past 1/1.25 of its capacity, in any view, is near
        assert not caps.roomy([room, dict(room, **{key: room[key] + 2})], A, N), key
    # the foresight's looser test: a first fit's headroom (1.1) to spare, which a 1.2x margin has and 1.05x has not
    near = dict(visible_anchors=int(slots / 1.2), active_gaussians=int(active / 1.2), pairs=int(pairs / 1.2))
    assert caps.roomy([near], A, N, headroom=capacity.FIT_HEADROOM) and not caps.roomy([near], A, N)
    tight = dict(near, pairs=int(pairs / 1.05))
    assert not caps.roomy([near, tight], A, N, headroom=capacity.FIT_HEADROOM)


def test_the_host_side_render_under_vmap_names_the_traceable_one():
    import jax
    import jax.numpy as jnp

    from cusgs_jax.training.capacity import ExactRender

    render = ExactRender(build=lambda capacities: None, capacities=None, n_offsets=4)
    with pytest.raises(TypeError, match=r"host-side.*cusgs_jax\.render\(model, cameras"):
        jax.vmap(lambda x: render(x))(jnp.zeros((2, 3)))


def test_a_fit_for_the_forecast_growth_scales_every_need_before_the_headroom():
    """``fill``: the start's fit for a run whose strategies will grow the alive anchors into the capacity (an
    accelerator's start, app/loop.growth_forecast): each need times ``fill``, then the usual buckets and headroom."""
    from cusgs_jax.training.capacity import Capacities, growth_fill

    needs = dict(visible_anchors=300, active_gaussians=1200, pairs=9000)
    tight = Capacities.fitted(needs, 1000, 10)
    assert Capacities.fitted(needs, 1000, 10, fill=1.0) == tight == Capacities.fitted(needs, 1000, 10, fill=0.5)
    assert growth_fill(alive=500, anchor_capacity=1000) == 2.0 and growth_fill(alive=2000, anchor_capacity=1000) == 1.0
    wide = Capacities.fitted(needs, 1000, 10, fill=2.0)
    doubled = {key: 2 * value for key, value in needs.items()}
    assert wide == Capacities.fitted(doubled, 1000, 10)
    assert wide.visible_slots(1000) >= 1.1 * 600 > tight.visible_slots(1000)
    assert wide.pairs(1000, 10) >= 1.25 * 18000 - 4096
