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
    foresight = Foresight([_Every(400, 100)], iterations=3000, eager=False)
    assert foresight.lead_steps([]) == MIN_LEAD_STEPS  # nothing measured yet
    for _ in range(10):
        foresight.stepped(0.2)
    assert foresight.lead_steps([12.0, 15.0]) == int(np.ceil(LEAD * 15.0 / 0.2))  # the slowest compile, 1.5x
    assert foresight.lead_steps([0.1]) == MIN_LEAD_STEPS
    seen = []

    def preview(session, loop, done, due):
        seen.append((done, due))
        return due == 400, []  # the update at 400 comes near the capacities; the one at 500 leaves room to spare

    foresight._preview = preview
    session = types.SimpleNamespace(ahead=types.SimpleNamespace(enabled=True, compile_seconds=[4.0]))
    loop = types.SimpleNamespace(state=None)
    foresight._next_capacities = lambda session, loop, done: []
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
    foresight = Foresight([grower, pruner], iterations=1000, eager=False)
    seen = []
    foresight._preview = lambda session, loop, done, due: (seen.append(due), (False, []))[1]
    foresight._next_capacities = lambda session, loop, done: []
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


def test_the_next_capacitys_step_is_prepared_for_the_work_capacities_the_growth_will_give(monkeypatch):
    from cusgs_jax.app import foresight as foresight_module
    from cusgs_jax.training.capacity import Capacities

    class Next(_Every):
        def next_capacity(self, state, step):
            return 1500

    grown = types.SimpleNamespace(anchors="grown")
    monkeypatch.setattr(foresight_module.jax, "eval_shape", lambda fn, state: grown)
    foresight = Foresight([Next(400, 100)], iterations=1000)
    caps = Capacities(visible_fraction=0.5, active_fraction=0.5, pairs_per_active=4.0)
    session = types.SimpleNamespace(cfg=types.SimpleNamespace(model=types.SimpleNamespace(n_offsets=10)),
                                    batches=lambda step: {})
    loop = types.SimpleNamespace(state=types.SimpleNamespace(anchors=types.SimpleNamespace(capacity=1000), step=0),
                                 capacities=caps, tx=None)
    requests = foresight._next_capacities(session, loop, 10)
    assert foresight._next_capacities(session, loop, 20) == []  # asked once per anchor capacity
    # what the loop's growth will run, with the evaluation render for the grown anchors
    assert requests == [foresight_module.Request(caps.regrown(1000, 1500, 10), grown, render=True)]
    assert requests[0].capacities.active_fraction < caps.active_fraction


def test_the_work_bound_is_the_recent_most_plus_what_the_grown_anchors_can_add():
    foresight = Foresight([], iterations=100)
    assert foresight.work_bound(alive=100, grown=5, n_offsets=4) is None  # no step seen yet
    foresight.stepped(0.1, dict(visible_anchors=40, active_gaussians=120, pairs=600, loss=1.0))
    foresight.stepped(0.1, dict(visible_anchors=50, active_gaussians=100, pairs=480))
    # visible 50 + 5, active 120 + 5·4, pairs 600 · 140 / 120
    assert foresight.work_bound(alive=100, grown=5, n_offsets=4) == dict(visible_anchors=55, active_gaussians=140,
                                                                         pairs=700)
    # never more than the alive anchors can give
    assert foresight.work_bound(alive=52, grown=5, n_offsets=2) == dict(visible_anchors=52, active_gaussians=104,
                                                                        pairs=520)


def _preview_case(monkeypatch, visible: int, grown: int):
    """A foresight one step before an update that grows ``grown`` anchors, after a step that needed ``visible``
    visible anchors; returns (whether it asks for a second look, the views it measured, the programs prepared)."""
    import cusgs_jax.app.foresight as foresight_module
    from cusgs_jax.densify.base import UpdateInfo
    from cusgs_jax.training.capacity import Capacities

    capacities, capacity, n_offsets = Capacities(0.5, 0.25, 3.0), 1000, 4
    alive = np.zeros(capacity, bool)
    alive[:600] = True
    state = types.SimpleNamespace(anchors=types.SimpleNamespace(capacity=capacity, alive=alive), nets={})

    class Grower(_Every):
        def update(self, state, tx, step):
            grown_alive = state.anchors.alive.copy()
            grown_alive[600:600 + grown] = True
            return types.SimpleNamespace(anchors=types.SimpleNamespace(capacity=capacity, alive=grown_alive),
                                         nets={}), UpdateInfo(grown=grown)

    measured = []
    monkeypatch.setattr(foresight_module, "_copy", lambda s: s)
    monkeypatch.setattr(foresight_module, "view_needs", lambda anchors, nets, views, cfg: measured.extend(views) or [
        dict(visible_anchors=visible + grown, active_gaussians=100, pairs=300) for _ in views])
    foresight = Foresight([Grower(400, 100)], iterations=1000)
    foresight.stepped(0.1, dict(visible_anchors=visible, active_gaussians=100, pairs=300))
    session = types.SimpleNamespace(cfg=types.SimpleNamespace(model=types.SimpleNamespace(n_offsets=n_offsets),
                                                              train=types.SimpleNamespace(batch_size=1)),
                                    batches=lambda step: dict(camera=step, index=step))
    loop = types.SimpleNamespace(state=state, capacities=capacities, tx=None)
    assert capacities.visible_slots(capacity) == 500
    near, requests = foresight._preview(session, loop, 399, 400)
    return near, measured, requests


def test_a_preview_whose_bound_leaves_room_measures_no_views(monkeypatch):
    near, measured, prepared = _preview_case(monkeypatch, visible=300, grown=20)  # 320 · 1.1 fits 500 slots
    assert not near and measured == [] and prepared == []


def test_a_preview_near_the_capacities_measures_the_next_views(monkeypatch):
    near, measured, prepared = _preview_case(monkeypatch, visible=440, grown=20)  # 460 · 1.1 does not fit 500
    assert near and len(measured) == 8 and prepared  # PREVIEW_STEPS views; the step prepared at least once


def test_the_plan_is_the_updates_capacities_then_each_replays_from_plain_values():
    """``plan`` takes plain values: the capacities now, the anchor capacity before and after, the views' needs."""
    from cusgs_jax.app.foresight import plan
    from cusgs_jax.training.capacity import Capacities

    caps = Capacities(0.5, 0.25, 3.0)
    assert plan(caps, 1000, 1000, [dict(visible_anchors=10, active_gaussians=10, pairs=10)], 4) == [caps]
    planned = plan(caps, 1000, 1000, [dict(visible_anchors=600, active_gaussians=100, pairs=300)], 4)
    assert planned[0] == caps and planned[1].visible_fraction > 0.5 and len(planned) == 2
    grown = plan(caps, 1000, 1500, [], 4)
    assert grown == [caps.regrown(1000, 1500, 4)]


def test_a_preview_silences_its_own_thread_only(caplog):
    """The preview's update would announce a growth that has not happened: its thread's records are dropped while
    another thread's (a background compile's) still reach the log."""
    import logging
    import threading

    from cusgs_jax.app.foresight import _quiet

    logger = logging.getLogger("cusgs_jax")
    with caplog.at_level("INFO", logger="cusgs_jax"):
        with _quiet():
            logger.info("from the preview")
            other = threading.Thread(target=lambda: logger.info("from another thread"))
            other.start()
            other.join()
        logger.info("after the preview")
    assert "from another thread" in caplog.text and "from the preview" not in caplog.text
    assert "after the preview" in caplog.text


def test_the_lead_follows_the_recent_compiles_and_an_eager_foresight_looks_as_soon_as_it_can():
    """On an accelerator (eager) the first look at an update comes right after the update before it, the second at
    the lead; the lead itself follows the recent compiles' seconds (the machine's load now, not its worst)."""
    from cusgs_jax.app.foresight import RECENT_COMPILES

    foresight = Foresight([_Every(400, 100)], iterations=1000, eager=False)
    for _ in range(5):
        foresight.stepped(0.1)
    assert foresight.lead_steps([30.0] + [2.0] * RECENT_COMPILES) == int(np.ceil(LEAD * 2.0 / 0.1))
    eager = Foresight([_Every(400, 100)], iterations=1000, eager=True)
    seen = []
    eager._preview = lambda session, loop, done, due: (seen.append((done, due)), (True, []))[1]
    eager._next_capacities = lambda session, loop, done: []
    session = types.SimpleNamespace(ahead=types.SimpleNamespace(enabled=True, compile_seconds=[4.0]))
    for done in range(1, 450):
        eager.after(session, types.SimpleNamespace(state=None), done)
    assert seen[0] == (1, 400) and seen[1][1] == 400 and 400 - seen[1][0] == max(MIN_LEAD_STEPS, eager.lead_steps([4.0]))
    assert seen[2] == (400, 500)  # the next update's first look: right after the one before it
