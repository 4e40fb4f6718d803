"""Which programs the training loop will need next, found early enough to compile them in the background.

A run changes its step's program at three moments: a strategy grows the anchor capacity, a view
after an update needs more visible slots, active Gaussians or tile pairs than the step has (a
replay, :mod:`cusgs_jax.training.capacity`), or pruning shrinks the capacity. :class:`Foresight`
prepares the first two (:meth:`cusgs_jax.app.ahead.Program.prepare`) a compile's time before they
happen:

* **the update's preview.** When the next strategy update is about one compile away (the measured
  seconds of a background compile over the median step's, times :data:`LEAD`), and again at half
  that lead (the statistics an update reads are then nearer to what it will read) unless the first look
  left every capacity the headroom of a first fit to spare (:data:`~cusgs_jax.training.capacity.FIT_HEADROOM`,
  :meth:`~cusgs_jax.training.capacity.Capacities.roomy`), the update is run on
  a copy of the state; the views of the :data:`PREVIEW_STEPS` steps after it are measured on the
  preview (:func:`cusgs_jax.training.render.view_needs`), and the step is compiled for the preview's
  anchor capacity at every capacities those views would grow the run to
  (:meth:`~cusgs_jax.training.capacity.Capacities.replayed`). Measuring those views costs about two
  steps; it is skipped when the update keeps the anchor capacity and a bound on what any view will need
  after it (:meth:`Foresight.work_bound`: the most the recent steps needed, plus what the grown anchors
  can add) leaves every capacity a first fit's headroom: nothing is then compiled, as the measurement
  would have found;
* **a strategy's next capacity** (:meth:`cusgs_jax.densify.base.Strategy.next_capacity`): the
  anchor capacity a strategy says its next growth would move to, with the work capacities a growth gives
  (:meth:`~cusgs_jax.training.capacity.Capacities.regrown`).

The evaluation render is prepared for a new anchor capacity too. The foresight only plans: it returns
:class:`Request` s (which capacities, for which state's types) and the loop hands them to the one owner of the
step's programs (:class:`cusgs_jax.app.programs.StepPrograms`); which capacities a run will pass through is the
pure :func:`plan`. A forecast that misses costs what it cost without one (a deferred view, or a compile on the
loop's path where nothing is compiled in the background); a forecast never changes a capacity, so the run's
numbers are those of a run without it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import statistics
import threading
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.densify import ops
from cusgs_jax.training.capacity import FIT_HEADROOM, WORK_KEYS, Capacities
from cusgs_jax.training.render import view_needs

log = logging.getLogger("cusgs_jax")

LEAD = 1.5  # the preview comes this many compile times before the update it previews
MIN_LEAD_STEPS = 10  # and at least this many steps before it
PREVIEW_STEPS = 8  # the steps after an update whose views say which capacities to compile ahead
PREVIEWS = 2  # previews of one update: at the lead and at half of it (each may start a compile)
RECENT_STEPS = 50  # the step time is the median of this many recent steps, and their work bounds the next ones'
RECENT_COMPILES = 3  # the lead follows the slowest of this many recent background compiles
CAPACITY_CHECK_EVERY = 10  # steps between asking the strategies for their next capacity (a host transfer)


@dataclasses.dataclass(frozen=True)
class Request:
    """A program the loop will likely need: the step with ``capacities`` on a train state of ``state``'s types
    (arrays or ``ShapeDtypeStruct`` s), and with ``render`` the evaluation render for ``state.anchors`` too."""

    capacities: Capacities
    state: Any
    render: bool = False


def plan(current: Capacities, anchor_capacity: int, new_capacity: int, needs: list[dict],
         n_offsets: int) -> list[Capacities]:
    """The work capacities a run stepping with ``current`` passes through after an update that moves the anchor
    capacity from ``anchor_capacity`` to ``new_capacity`` (equal: unchanged), on steps whose views need ``needs``
    ({"visible_anchors", "active_gaussians", "pairs"} each): the update's own
    (:meth:`~cusgs_jax.training.capacity.Capacities.regrown`), then each replay's
    (:meth:`~cusgs_jax.training.capacity.Capacities.replayed`), in order. Plain values in, plain values out."""
    after = current.regrown(anchor_capacity, new_capacity, n_offsets)
    return [after, *after.replayed(needs, new_capacity, n_offsets)]


class Foresight:
    """Plans the programs of the steps after the next strategy update (see the module docstring).

    Args:
      strategies: the run's densification strategies; iterations: ``train.iterations``.
      eager: preview each update as soon as the one before it is done (as early as it can be known), and again at
        the lead. Default: on an accelerator, whose host cores are idle while the device trains (a compile there
        costs the run nothing, a late one a deferred view or a wait); on a CPU a compile shares the steps' cores,
        so the first look comes at the lead.
    """

    def __init__(self, strategies, iterations: int, eager: bool | None = None):
        self.strategies, self.iterations = tuple(strategies), iterations
        self.eager = jax.default_backend() != "cpu" if eager is None else bool(eager)
        self._recent: list[float] = []
        self._needs: list[dict] = []  # the recent steps' work (visible anchors, active Gaussians, tile pairs)
        self._next_due: int | None = None
        self._previewed: set[int] = set()
        self._asked: set[int] = set()  # anchor capacities already prepared from next_capacity

    def stepped(self, seconds: float, metrics: dict | None = None) -> None:
        """One step's wall seconds (for the lead in steps) and its ``metrics`` (host values of a step that dropped
        nothing: ``visible_anchors``, ``active_gaussians``, ``pairs``, what its views needed)."""
        self._recent = (self._recent + [seconds])[-RECENT_STEPS:]
        if metrics is not None:
            self._needs = (self._needs + [{key: int(metrics[key]) for key in WORK_KEYS}])[-RECENT_STEPS:]

    def work_bound(self, alive: int, grown: int, n_offsets: int) -> dict | None:
        """What a view may need after an update that placed ``grown`` anchors and left ``alive`` alive: the most
        the last :data:`RECENT_STEPS` steps needed, plus one visible anchor and ``n_offsets`` active Gaussians for
        each grown anchor (never more than ``alive`` has), tile pairs in proportion to the active Gaussians.
        None before any step was seen. A bound on the recent views, an estimate for others: a wrong one costs a
        compile on the loop's path, never a result."""
        if not self._needs:
            return None
        recent = {key: max(need[key] for need in self._needs) for key in WORK_KEYS}
        visible = min(alive, recent["visible_anchors"] + grown)
        active = min(alive * n_offsets, recent["active_gaussians"] + grown * n_offsets)
        pairs = math.ceil(recent["pairs"] * active / max(recent["active_gaussians"], 1))
        return dict(visible_anchors=visible, active_gaussians=active, pairs=pairs)

    def _due_after(self, done: int) -> int | None:
        """The next update after ``done`` steps that may need new programs: one that can add anchors or
        capacity (an update that only removes anchors — a pruning pass, an early cull — needs none)."""
        if self._next_due is None or self._next_due <= done:
            self._next_due = next((d for d in range(done + 1, self.iterations + 1)
                                   if any(s.due(d) and not only_removes(s, d) for s in self.strategies)), None)
        return self._next_due

    def lead_steps(self, compile_seconds: list[float]) -> int:
        """Steps before an update at which its preview runs: :data:`LEAD` background compiles' worth — the slowest
        of the last :data:`RECENT_COMPILES` (measured on this machine, so the lead follows its load) over the
        median of the recent steps."""
        if not self._recent or not compile_seconds:
            return MIN_LEAD_STEPS
        step = max(statistics.median(self._recent), 1e-6)
        return max(MIN_LEAD_STEPS, math.ceil(LEAD * max(compile_seconds[-RECENT_COMPILES:]) / step))

    def _look_leads(self, lead: int) -> tuple[float, ...]:
        """How many steps before the update each of the :data:`PREVIEWS` looks may come."""
        if self.eager:
            return (math.inf, *(max(lead >> (look - 1), MIN_LEAD_STEPS) for look in range(1, PREVIEWS)))
        return tuple(max(lead >> look, MIN_LEAD_STEPS) for look in range(PREVIEWS))

    def after(self, session, loop, done: int) -> list[Request]:
        """After ``done`` completed steps (and their strategy updates) of ``session``'s ``loop``
        (:class:`cusgs_jax.app.session.Session`, :class:`~cusgs_jax.app.loop.Loop`): the programs to compile
        ahead now (the loop hands them to its :class:`~cusgs_jax.app.programs.StepPrograms`)."""
        ahead = session.ahead
        if ahead is None or not ahead.enabled:
            return []
        requests = self._next_capacities(session, loop, done) if done % CAPACITY_CHECK_EVERY == 0 else []
        due = self._due_after(done)
        if due is None:
            return requests
        leads = self._look_leads(self.lead_steps(ahead.compile_seconds))
        for look in range(PREVIEWS):  # at the lead, then at half of it: a later preview sees more of the statistics
            if (due, look) not in self._previewed and due - done <= leads[look]:
                self._previewed.update((due, earlier) for earlier in range(look + 1))
                near, previewed = self._preview(session, loop, done, due)
                if not near:  # room to spare: a second look would find it too
                    self._previewed.update((due, later) for later in range(PREVIEWS))
                return requests + previewed
        return requests

    def _next_capacities(self, session, loop, done: int) -> list[Request]:
        state, requests = loop.state, []
        for strategy in self.strategies:
            capacity = strategy.next_capacity(state, done) if hasattr(strategy, "next_capacity") else None
            if capacity is None or capacity == state.anchors.capacity or capacity in self._asked:
                continue
            self._asked.add(capacity)
            grown = jax.eval_shape(lambda s, c=capacity: ops.grow_capacity(s, loop.tx, c), state)
            log.debug("compiling ahead the step for %d anchor slots (%s's next capacity)", capacity, strategy.name)
            caps = loop.capacities.regrown(state.anchors.capacity, capacity, session.cfg.model.n_offsets)
            requests.append(Request(caps, grown, render=True))
        return requests

    def _preview(self, session, loop, done: int, due: int) -> tuple[bool, list[Request]]:
        """Preview the update due after ``due`` steps: what the steps after it need compiled, and whether they come
        near the run's capacities (an anchor capacity of its own, or a view needing more than
        1/:data:`~cusgs_jax.training.capacity.FIT_HEADROOM` of a work capacity)."""
        cfg = session.cfg
        preview, grown = _copy(loop.state), 0  # an update may donate the arrays it is given
        with _quiet():
            for strategy in self.strategies:
                if strategy.due(due):
                    preview, info = strategy.update(preview, loop.tx, due)
                    grown += info.grown
        capacity = preview.anchors.capacity
        if capacity == loop.state.anchors.capacity:
            bound = self.work_bound(int(np.sum(np.asarray(preview.anchors.alive))), grown, cfg.model.n_offsets)
            if bound is not None and loop.capacities.roomy([bound], capacity, cfg.model.n_offsets,
                                                           headroom=FIT_HEADROOM):
                log.debug("step %d: the update at %d leaves room to spare (%s): no views measured", done, due, bound)
                return False, []
        steps = range(due, min(due + PREVIEW_STEPS, self.iterations))
        batches = [session.batches(step) for step in steps]
        if not batches:
            return False, []
        size = cfg.train.batch_size
        views = [(b["camera"], b["index"]) for b in batches] if size == 1 else [
            (jax.tree_util.tree_map(lambda x, v=v: x[v], b["camera"]), b["index"][v]) for b in batches
            for v in range(size)]
        needs = view_needs(preview.anchors, preview.nets, views, cfg)
        planned = plan(loop.capacities, loop.state.anchors.capacity, capacity, needs, cfg.model.n_offsets)
        grows = capacity != loop.state.anchors.capacity
        requests = [Request(caps, preview, render=grows and i == 0) for i, caps in enumerate(planned)]
        log.debug("step %d: the steps after the update at %d (%d anchor slots) need %s", done, due, capacity, planned)
        return grows or not planned[0].roomy(needs, capacity, cfg.model.n_offsets, headroom=FIT_HEADROOM), requests


def only_removes(strategy, step: int) -> bool:
    """:meth:`~cusgs_jax.densify.base.Strategy.only_removes` (False for a strategy without the hook)."""
    hook = getattr(strategy, "only_removes", None)
    return bool(hook(step)) if hook is not None else False


@jax.jit
def _copy(state):
    """A copy of ``state`` (one program, not one per array)."""
    return jax.tree_util.tree_map(jnp.copy, state)


class _OtherThreads(logging.Filter):
    """Lets through the records of every thread but one."""

    def __init__(self, thread: int):
        super().__init__()
        self.thread = thread

    def filter(self, record: logging.LogRecord) -> bool:
        return record.thread != self.thread


@contextlib.contextmanager
def _quiet():
    """The package's log silenced on this thread (a preview's update would announce a growth that has not
    happened); other threads — a background compile's, a viewer's — log as ever."""
    logger, only = logging.getLogger("cusgs_jax"), _OtherThreads(threading.get_ident())
    logger.addFilter(only)
    try:
        yield
    finally:
        logger.removeFilter(only)
