"""StepPrograms (app/programs.py): one program per capacities, and its own counts of recompilations and replays."""

from __future__ import annotations

from cusgs_jax.app.programs import StepPrograms
from cusgs_jax.training.capacity import Capacities

START = Capacities(visible_fraction=0.5, active_fraction=0.5, pairs_per_active=4.0)
WIDER = Capacities(visible_fraction=0.75, active_fraction=0.5, pairs_per_active=4.0)


def _programs():
    built = []

    def build(capacities):
        built.append(capacities)
        return lambda state, batch: (state, {})

    return StepPrograms(build, START, n_offsets=4), built


def test_one_program_per_capacities_built_once():
    steps, built = _programs()
    assert steps.program() is steps.program(START)
    steps.program(WIDER)
    steps.program(WIDER)
    assert built == [START, WIDER]


def test_covers_asks_for_every_fraction():
    steps, _ = _programs()
    assert steps.covers(START)
    assert not steps.covers(WIDER)
    assert not steps.covers(Capacities(0.5, 0.5, 4.5))
    assert steps.covers(Capacities(0.25, 0.5, 1.0))


def test_a_replay_counts_itself_and_recompiles_only_for_capacities_the_step_lacks():
    steps, _ = _programs()
    assert steps.replay() == START and (steps.replays, steps.recompilations) == (1, 0)  # a deferred view, as it was
    assert steps.replay(Capacities(0.25, 0.5, 1.0)) == START and (steps.replays, steps.recompilations) == (2, 0)
    assert steps.replay(WIDER) == WIDER and (steps.replays, steps.recompilations) == (3, 1)


def test_grow_replays_with_grown_capacities_and_regrow_refit_count_as_recompilations():
    steps, _ = _programs()
    capacity, n = 1000, 4
    needs = dict(visible_anchors=900, dropped_anchors=400, active_gaussians=100, dropped_gaussians=0,
                 pairs=10, dropped_pairs=0)
    grown = steps.grow(needs, capacity)
    assert grown.visible_fraction >= 0.9 and (steps.replays, steps.recompilations) == (1, 1)
    steps.regrow(capacity, 2 * capacity)
    steps.refit(START)
    assert steps.capacities == START and (steps.replays, steps.recompilations) == (1, 3)
    assert n == steps.n_offsets
