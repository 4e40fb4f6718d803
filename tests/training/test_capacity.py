"""Work capacities (training/capacity.py): bucketed growth rules and what they are applied to."""

from __future__ import annotations

import pytest

from cusgs_jax.config import Config
from cusgs_jax.training import capacity


def test_visible_fraction_grows_in_buckets_to_hold_what_was_seen_and_stops_at_one():
    grown = capacity.grown_visible_fraction(0.1, needed_slots=300, capacity=1000)
    assert grown * 1000 >= 1.1 * 300 and grown * capacity.FRACTION_BUCKET == int(grown * capacity.FRACTION_BUCKET)
    assert capacity.grown_visible_fraction(0.6, needed_slots=601, capacity=1000) == 0.75  # at least one bucket
    assert capacity.grown_visible_fraction(0.9, needed_slots=1000, capacity=1000) == 1.0
    # few distinct sizes: a run that keeps seeing slightly more grows in coarse steps
    sizes = {capacity.grown_visible_fraction(0.125, needed, 1000) for needed in range(130, 900, 7)}
    assert len(sizes) <= capacity.FRACTION_BUCKET


def test_pair_capacity_grows_by_half_steps_with_headroom():
    grown = capacity.grown_pairs_per_gaussian(3.0, needed_pairs=50_000, num_gaussians=10_000)
    assert capacity.max_pairs(grown, 10_000) >= 50_000 * 1.2
    assert grown >= 4.5 and (2 * grown) == int(2 * grown)
    assert capacity.grown_pairs_per_gaussian(3.0, needed_pairs=10, num_gaussians=10) == 4.5  # ≥ 1.5×


def test_grow_for_grows_the_slots_first_then_the_pairs():
    cfg = Config().replace(model=dict(visible_fraction=0.25))
    both = dict(visible_anchors=250, dropped_anchors=100, pairs=900, dropped_pairs=50)
    grown = capacity.grow_for(cfg, both, capacity=1000, num_gaussians=2500)
    assert grown.model.visible_fraction > 0.25 and grown.splat == cfg.splat  # the replay measures pairs anew
    pairs_only = dict(visible_anchors=250, dropped_anchors=0, pairs=9000, dropped_pairs=5000)
    grown = capacity.grow_for(cfg, pairs_only, capacity=1000, num_gaussians=250)
    assert grown.model == cfg.model and grown.splat.max_pairs_per_gaussian > cfg.splat.max_pairs_per_gaussian
    assert capacity.grow_for(cfg, dict(visible_anchors=3, dropped_anchors=0, pairs=1, dropped_pairs=0), 10, 40) == cfg


def test_saved_capacities_are_restored_but_never_shrink_the_configured_ones():
    grown = Config().replace(model=dict(visible_fraction=0.875), splat=dict(max_pairs_per_gaussian=6.0))
    saved = capacity.capacities(grown)
    assert capacity.with_capacities(Config(), saved) == grown
    bigger = Config().replace(model=dict(visible_fraction=1.0))
    assert capacity.with_capacities(bigger, saved).model.visible_fraction == 1.0
    assert capacity.with_capacities(Config(), None) == Config()
    with pytest.raises(KeyError):
        capacity.with_capacities(Config(), {"visible_fraction": 1.0})
