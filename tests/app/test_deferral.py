"""app/deferral.py: the queue of fresh and deferred batch positions, and a loop that trains around a late program."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cusgs_jax.app.deferral import MAX_DEFERRED, MAX_TRIES, ViewQueue


def test_every_position_is_trained_once_whatever_is_deferred():
    """A random mix of deferrals and late programs: the queue hands out each position 0..T-1 exactly once."""
    rng = np.random.default_rng(0)
    queue, trained, updates = ViewQueue(next=0, total=200), [], 0
    ready = set()
    while queue.fresh_left() or queue.waiting:
        item = queue.take_ready(lambda caps: caps in ready)
        if item is None and queue.must_wait(0):
            item = queue.take_oldest()
        if item is not None:
            trained.append(item.position)
            queue.trained(item, updates)
        else:
            position = queue.take_fresh()
            if rng.uniform() < 0.2:
                queue.defer(position, int(rng.integers(0, 5)), updates)
                continue
            trained.append(position)
        updates += 1
        if rng.uniform() < 0.05:
            ready.add(int(rng.integers(0, 5)))
    assert sorted(trained) == list(range(200)) and updates == 200
    assert queue.deferred > 10 and queue.trained_late == queue.deferred and queue.steps_late_max > 0


def test_the_loop_waits_only_when_no_fresh_view_is_left_too_many_are_deferred_or_every_view_overflows():
    queue = ViewQueue(next=0, total=10)
    assert not queue.must_wait(tries=MAX_TRIES)  # nothing deferred: nothing to wait for
    queue.defer(queue.take_fresh(), "grown", 0)
    assert not queue.must_wait(tries=MAX_TRIES - 1) and queue.must_wait(tries=MAX_TRIES)
    assert queue.take_ready(lambda caps: False) is None
    queue.next = 10  # no fresh view left
    assert queue.must_wait(tries=0)
    many = ViewQueue(next=0, total=1000)
    for _ in range(MAX_DEFERRED):
        many.defer(many.take_fresh(), "grown", 0)
    assert many.must_wait(tries=0)


def test_a_changed_anchor_capacity_lets_every_deferred_view_try_again():
    queue = ViewQueue(next=0, total=10)
    queue.defer(queue.take_fresh(), "grown", 0)
    queue.reset_capacities()
    item = queue.take_ready(lambda caps: False)
    assert item is not None and item.position == 0


def test_a_checkpoint_keeps_the_deferred_positions_and_the_counts():
    queue = ViewQueue(next=0, total=50)
    for _ in range(5):
        queue.take_fresh()
    queue.defer(2, "grown", 3)
    queue.waited(1.5)
    saved = queue.as_dict()
    back = ViewQueue.restored(saved, updates=4, total=50)
    assert back.next == 5 and [i.position for i in back.waiting] == [2] and back.waiting[0].capacities is None
    assert back.deferred == 1 and back.waits == 1 and back.waited_s == 1.5
    assert ViewQueue.restored(None, updates=7, total=50).next == 7  # written before deferral: all below trained
    assert set(queue.record()) == {"views", "waits", "waited_s", "steps_late_max", "steps_late_mean",
                                   "seconds_late_max"}


def _blind():
    from cusgs_jax.app.foresight import Foresight

    class Blind(Foresight):
        """A forecast that misses on purpose: it prepares nothing."""

        def after(self, session, loop, done):
            return []

    return Blind


@pytest.mark.parametrize("delay_s", [2.0])
def test_a_late_program_defers_the_view_that_needs_it_and_the_loop_trains_the_others(tiny_scene, tmp_path, delay_s):
    """Issue 46's machine-independent check: every background compile starts ``delay_s`` late and the forecast
    prepares nothing, so each growth's program is late. The loop trains the views that fit meanwhile (the view
    that overflowed is trained later, each position once); it waits only when no fresh view is left."""
    from cusgs_jax.app.ahead import Ahead
    from cusgs_jax.app.loop import start, train
    from cusgs_jax.app.session import setup
    from cusgs_jax.testing.runs import tiny_config

    iterations = 300
    cfg = tiny_config(tiny_scene, f"train.iterations={iterations}", "eval.every=0", "train.checkpoint_every=0",
                      "grow.start=400", "grow.stop=400", "prune.start=400", "train.defer_views=true")
    with Ahead() as ahead:
        session = setup(cfg, tmp_path / "run", ahead=ahead)
        loop = start(session)
        ahead.delay_s = delay_s  # the start's programs are in; every later compile is late
        calls = []
        batches = session.batches
        session = dataclasses.replace(session, batches=lambda position: calls.append(position) or batches(position))
        train(session, loop, foresight=_blind()(session.strategies, iterations))
    queue = loop.views
    assert int(loop.state.step) == iterations and queue.next == iterations and not queue.waiting
    assert sorted(set(calls)) == list(range(iterations))  # every position trained (the deferred ones again)
    assert queue.deferred >= 1 and queue.trained_late >= 1 and queue.steps_late_max >= 1, queue.as_dict()
    assert loop.replays >= 1 and loop.recompilations >= 1
    # the loop did not stand still for the late program: it trained other views while it compiled (a compile
    # starts >= delay_s late, a step of this scene takes milliseconds)
    assert queue.steps_late_max >= 10, queue.as_dict()
    session.ckpt.close()


def test_without_background_compiles_nothing_is_deferred(tiny_scene, tmp_path):
    """With compiling ahead off a grown program compiles on the call: the loop replays at once, in order."""
    from cusgs_jax.app.ahead import Ahead
    from cusgs_jax.app.loop import start, train
    from cusgs_jax.app.session import setup
    from cusgs_jax.testing.runs import tiny_config

    cfg = tiny_config(tiny_scene, "eval.every=0", "train.checkpoint_every=0")
    with Ahead(enabled=False) as ahead:
        session = setup(cfg, tmp_path / "run", ahead=ahead)
        loop = start(session)
        train(session, loop)
    assert loop.views.deferred == 0 and loop.views.next == cfg.train.iterations
    session.ckpt.close()


@pytest.mark.slow  # 45 s on a loaded 2-core machine; the deferring loop's own test stays in the default run
def test_with_defer_views_off_a_late_program_is_waited_for_and_nothing_changes_order(tiny_scene, tmp_path):
    """``train.defer_views=false``: the loop waits for a late program (the numbers never depend on when a background
    compile finished); nothing is deferred, the replay still happens."""
    from cusgs_jax.app.ahead import Ahead
    from cusgs_jax.app.loop import start, train
    from cusgs_jax.app.session import setup
    from cusgs_jax.testing.runs import tiny_config

    iterations = 20
    cfg = tiny_config(tiny_scene, f"train.iterations={iterations}", "eval.every=0", "train.checkpoint_every=0",
                      "grow.start=400", "grow.stop=400", "prune.start=400")
    assert cfg.train.defer_views is False  # the tests' runs compare bit for bit
    with Ahead() as ahead:
        session = setup(cfg, tmp_path / "run", ahead=ahead)
        loop = start(session)
        # a step too narrow for most views (visible slots), whose growth needs a program not compiled yet
        narrow = dataclasses.replace(loop.capacities, visible_fraction=0.25, pairs_per_active=1.0)
        loop.steps.capacities = narrow
        batch = session.batches(0)
        loop.steps.prepare(narrow, loop.state, batch)
        loop.steps.program().wait(loop.state, batch)
        ahead.delay_s = 1.0
        train(session, loop, foresight=_blind()(session.strategies, iterations))
    assert loop.views.deferred == 0 and loop.views.next == iterations and loop.replays >= 1
    session.ckpt.close()
