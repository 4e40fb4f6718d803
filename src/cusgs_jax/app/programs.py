"""The train step's programs and the work capacities the loop steps with: one owner of what the step compiles.

:class:`StepPrograms` holds one :class:`~cusgs_jax.app.ahead.Program` per
:class:`~cusgs_jax.training.capacity.Capacities` (each with an executable per anchor capacity it was prepared or
called for), the capacities the loop steps with now, and its own counts: ``recompilations`` (every change of the
step's program: a replay's growth, an anchor capacity a strategy grew or pruning shrank) and ``replays`` (steps run
again with grown capacities). Everything that changes the step's program goes through it —
:meth:`StepPrograms.grow`, :meth:`~StepPrograms.regrow`, :meth:`~StepPrograms.refit` — and what the
foresight plans is compiled through it (:meth:`~StepPrograms.prepare`); :meth:`~StepPrograms.ready` says, without
waiting, whether a call would have to wait for a compile (the loop then trains on other views,
:mod:`cusgs_jax.app.deferral`).
"""

from __future__ import annotations

from collections.abc import Callable

from cusgs_jax.app.ahead import Ahead, Program
from cusgs_jax.training.capacity import Capacities


class StepPrograms:
    """The step's programs per work capacities, and the capacities the loop steps with.

    Args:
      build: ``build(capacities) -> step`` (a jitted ``step(state, batch) -> (state, metrics)``,
        :func:`~cusgs_jax.training.step.make_train_step` for the run's settings).
      capacities: the capacities the loop starts with.
      n_offsets: N (the capacities' active Gaussians and pairs count S·N).
      ahead: the run's background compiles (None: every program compiles on its first call).
    """

    def __init__(self, build: Callable[[Capacities], Callable], capacities: Capacities, n_offsets: int,
                 ahead: Ahead | None = None):
        self.build, self.capacities, self.n_offsets, self.ahead = build, capacities, n_offsets, ahead
        self.programs: dict[Capacities, Program] = {}
        self.recompilations = 0  # changes of the step's program (capacity growths and anchor capacity changes)
        self.replays = 0  # steps run again with grown capacities

    def program(self, capacities: Capacities | None = None) -> Program:
        """The step's :class:`~cusgs_jax.app.ahead.Program` for ``capacities`` (default: the current ones)."""
        capacities = self.capacities if capacities is None else capacities
        if capacities not in self.programs:
            self.programs[capacities] = Program(self.build(capacities), self.ahead)
        return self.programs[capacities]

    def __call__(self, state, batch):
        """One step with the current capacities' program (waiting for its compile if it is under way)."""
        return self.program()(state, batch)

    def prepare(self, capacities: Capacities, state, batch) -> bool:
        """Compile the step for ``capacities`` and the types of ``state`` and ``batch`` (arrays or
        ``ShapeDtypeStruct`` s) in the background; returns whether a compile was started."""
        return self.program(capacities).prepare(state, batch)

    def ready(self, capacities: Capacities, state, batch) -> bool:
        """Whether a step with ``capacities`` on arguments of these types runs without waiting for a compile
        (:meth:`~cusgs_jax.app.ahead.Program.ready`); always true when nothing is compiled in the background."""
        return self.program(capacities).ready(state, batch)

    def covers(self, capacities: Capacities) -> bool:
        """Whether the current capacities hold everything ``capacities`` hold (each fraction at least as large)."""
        current = self.capacities
        return (current.visible_fraction >= capacities.visible_fraction
                and current.active_fraction >= capacities.active_fraction
                and current.pairs_per_active >= capacities.pairs_per_active)

    def use(self, capacities: Capacities) -> None:
        """Step with ``capacities`` from now on (a new program: counted in ``recompilations``)."""
        self.capacities, self.recompilations = capacities, self.recompilations + 1

    def grown(self, metrics: dict, anchor_capacity: int, announce: bool = True) -> Capacities:
        """The current capacities grown for a step that reported dropped work
        (:meth:`~cusgs_jax.training.capacity.Capacities.grown`); nothing changes until :meth:`grow` or :meth:`use`."""
        return self.capacities.grown(metrics, anchor_capacity, self.n_offsets, announce=announce)

    def grow(self, metrics: dict, anchor_capacity: int) -> Capacities:
        """Grow for a step that dropped work, to replay it: :meth:`grown`, used; counts a replay."""
        return self.replay(self.grown(metrics, anchor_capacity))

    def replay(self, capacities: Capacities | None = None) -> Capacities:
        """A step runs (again) with ``capacities`` — a dropped step replayed, or a deferred view trained once its
        program is ready: they are used unless the current ones already hold them; counts a replay."""
        if capacities is not None and not self.covers(capacities):
            self.use(capacities)
        self.replays += 1
        return self.capacities

    def regrow(self, old_capacity: int, new_capacity: int) -> Capacities:
        """After a strategy changed the anchor capacity from ``old_capacity`` to ``new_capacity``
        (:meth:`~cusgs_jax.training.capacity.Capacities.regrown`): the step's program changes."""
        self.use(self.capacities.regrown(old_capacity, new_capacity, self.n_offsets))
        return self.capacities

    def refit(self, capacities: Capacities) -> None:
        """Capacities fitted anew (pruning shrank the anchor capacity): the step's program changes."""
        self.use(capacities)
