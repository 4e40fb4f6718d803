"""app/foresight.py: when the programs after a strategy update are prepared, and for which anchor capacity."""

from __future__ import annotations

import types

import numpy as np

from cusgs_jax.app.foresight import LEAD, MIN_LEAD_STEPS, PREVIEWS, Foresight
from cusgs_jax.config import GrowConfig, PruneConfig
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy
from cusgs_jax.densify.scaffold import NEXT_CAPACITY_USE, ScaffoldStrategy


class _Every:
    """A strategy due every ``interval`` steps from ``start``."""

    name = "every"

    def __init__(self, start, interval):
        self.start, self.interval = start, interval

    def due(self, step):
        return step >= self.start and (step - self.start) % self.interval == 0


def test_the_preview_comes_a_compile_before_the_update_and_again_at_half_that_when_near_the_capacities():
    foresight = Foresight([_Every(400, 100)], iterations=3000, step_program=None, prepare_render=None)
    assert foresight.lead_steps([]) == MIN_LEAD_STEPS  # nothing measured yet
    for _ in range(10):
        foresight.stepped(0.2)
    assert foresight.lead_steps([12.0, 15.0]) == int(np.ceil(LEAD * 15.0 / 0.2))  # the slowest compile, 1.5x
    assert foresight.lead_steps([0.1]) == MIN_LEAD_STEPS
    seen = []

    def preview(session, loop, done, due):
        seen.append((done, due))
        return due == 400  # the update at 400 comes near the capacities; the one at 500 leaves room to spare

    foresight._preview = preview
    session = types.SimpleNamespace(ahead=types.SimpleNamespace(enabled=True, compile_seconds=[4.0]))
    loop = types.SimpleNamespace(state=None)
    foresight._next_capacities = lambda session, loop, done: None
    for done in range(1, 520):
        foresight.after(session, loop, done)
    lead = foresight.lead_steps([4.0])  # 30 steps
    assert seen == [(400 - lead, 400), (400 - lead // 2, 400), (500 - lead, 500)]  # 500: no second look
    assert PREVIEWS == 2


def test_updates_that_only_remove_anchors_are_not_previewed():
    """A pruning pass clears alive bits: no view needs more after it, so only the grower's updates are previewed
    (the main job's passes after grow.stop, every 100 steps to step 3000, were previewed twice each before)."""
    grower = ScaffoldStrategy(GrowConfig(start=400, stop=600, interval=100), voxel_size=0.01, n_offsets=4, seed=0)
    pruner = FeaturePruneStrategy(PruneConfig(start=500, interval=100))
    assert pruner.only_removes(500) and not grower.only_removes(500)
    foresight = Foresight([grower, pruner], iterations=1000, step_program=None, prepare_render=None)
    seen = []
    foresight._preview = lambda session, loop, done, due: seen.append(due)
    foresight._next_capacities = lambda session, loop, done: None
    session = types.SimpleNamespace(ahead=types.SimpleNamespace(enabled=True, compile_seconds=[]))
    for done in range(1, 1000):
        foresight.after(session, types.SimpleNamespace(state=None), done)
    assert sorted(set(seen)) == [400, 500, 600]  # 500 and 600: the grower is due too; 700-900: the pruner alone


def test_scaffold_announces_its_next_capacity_once_the_slots_fill_up_while_it_still_grows():
    strategy = ScaffoldStrategy(GrowConfig(stop=1000, capacity_growth=1.5), voxel_size=0.01, n_offsets=4, seed=0)
    alive = np.zeros(1000, bool)
    state = types.SimpleNamespace(anchors=types.SimpleNamespace(capacity=1000, alive=alive))
    alive[: int(NEXT_CAPACITY_USE * 1000) - 1] = True
    assert strategy.next_capacity(state, 500) is None
    alive[: int(NEXT_CAPACITY_USE * 1000)] = True
    assert strategy.next_capacity(state, 500) == 1500  # ceil(A · grow.capacity_growth), what update grows to
    assert strategy.next_capacity(state, 1000) is None  # no growth after grow.stop
