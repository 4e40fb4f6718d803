"""The Strategy protocol: what a strategy sees of one rendered view (:class:`ViewRecord`), what
its host-side update reports (:class:`UpdateInfo`), what the run records of it (:class:`Tally`),
what its ``before_first_update`` hook may measure (:class:`Probe`), and the strategies a
configuration asks for (:func:`make_strategies`). The run loop (:mod:`cusgs_jax.app.run`) only
uses these; research code passes its own strategies as ``run(..., extra_strategies=...)``.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, S visible slots, N Gaussians
per anchor, G = S·N, F latent size.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Protocol

import jax

from cusgs_jax.config import Config
from cusgs_jax.run_folder import EvalRecord
from cusgs_jax.model.decode import to_slots


@dataclasses.dataclass(frozen=True)
class ViewRecord:
    """One view of the train step, as the ``accumulate`` hooks see it (traced values).

    Attributes:
      slots: :class:`cusgs_jax.model.decode.VisibleSlots` (slots [S], valid [S]).
      gaussians: the decoded :class:`cusgs_jax.model.decode.Gaussians` (G = S·N, slot order).
      render: the splatter's :class:`cusgs_jax.splat.RenderOutput` (visible [G], significance [G]).
      grad2d: [G, 2] ∂L/∂μ_2D in pixels.
      latent_grad: [S, F] ∂L/∂z of the gathered anchors.
      capacity: A; width, height: image size.
      step: [] int32 steps completed before this one; finite: [] bool, the update is applied.
    """

    slots: Any
    gaussians: Any
    render: Any
    grad2d: jax.Array
    latent_grad: jax.Array
    capacity: int
    width: int
    height: int
    step: jax.Array
    finite: jax.Array

    def to_slots(self, x: jax.Array, fill=0) -> jax.Array:
        """Scatter per-visible-slot values [S, ...] back to anchor slots [A, ...] (others ``fill``)."""
        return to_slots(x, self.slots, self.capacity, fill)


@dataclasses.dataclass(frozen=True)
class UpdateInfo:
    """What one host-side :meth:`Strategy.update` did; every strategy returns this type.

    The shell (:mod:`cusgs_jax.app.run`) adds it to the strategy's :class:`Tally` without
    knowing the strategy: the tally is logged in every ``metrics.jsonl`` row and in ``eval.json``
    (``densify``: {strategy name: tally}) and checkpointed.

    Attributes:
      grown: anchors placed into slots by this update (Python int).
      pruned: anchors whose ``alive`` bit this update cleared.
      capacity_changed: the anchor capacity A changed (new shapes: the jitted step retraces once).
      extra: further values of this update for the log, {name: JSON number} (e.g. ``alive``,
        ``capacity``, ``candidates``); the tally keeps the latest update's.
    """

    grown: int = 0
    pruned: int = 0
    capacity_changed: bool = False
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Tally:
    """What the run has recorded of one strategy (host side; checkpointed, so a resume continues it).

    Attributes:
      updates: updates run so far; grown, pruned: their sums; capacity_changes: updates that changed A.
      values: what :meth:`Strategy.before_first_update` returned (empty before the first update).
      last: the ``extra`` of the latest update.
    """

    updates: int = 0
    grown: int = 0
    pruned: int = 0
    capacity_changes: int = 0
    values: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    last: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def add(self, info: UpdateInfo) -> Tally:
        """This tally with one more update ``info``."""
        return dataclasses.replace(self, updates=self.updates + 1, grown=self.grown + int(info.grown),
                                   pruned=self.pruned + int(info.pruned),
                                   capacity_changes=self.capacity_changes + bool(info.capacity_changed),
                                   last={key: _plain(value) for key, value in info.extra.items()})

    def as_dict(self) -> dict:
        """JSON-ready: ``{"updates", "grown", "pruned", "capacity_changes", "values", "last"}``."""
        return dict(updates=self.updates, grown=self.grown, pruned=self.pruned,
                    capacity_changes=self.capacity_changes, values=dict(self.values), last=dict(self.last))

    @staticmethod
    def from_dict(record: Mapping[str, Any]) -> Tally:
        return Tally(**{field.name: record[field.name] for field in dataclasses.fields(Tally) if field.name in record})


def _plain(value):
    """A host scalar (jax/NumPy 0-d arrays → Python numbers) for JSON."""
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
        return value.item()
    return value


@dataclasses.dataclass(frozen=True)
class Probe:
    """What :meth:`Strategy.before_first_update` may look at of the run, nothing more.

    Attributes:
      step: completed steps (the update follows right after the hook).
      render_ms_per_view: measures the held-out render time per view (ms) of the model as it is now
        (compacted to its alive anchors); the training clock is paused while it runs, and it renders
        every evaluated view, so call it only when the value is wanted.
    """

    step: int
    render_ms_per_view: Callable[[], float]


class Strategy(Protocol):
    """A densification strategy (gsplat ``strategy/`` style). Subclass it to inherit the no-op hooks.

    Required:

    * ``name``: unique key of the strategy's state in ``TrainState.densify`` and of its tally.
    * ``init_state(capacity) -> stats``: fresh statistics for A = ``capacity`` slots (a
      :class:`~cusgs_jax.model.anchors.PerAnchor` pytree for per-anchor rows, so
      :mod:`cusgs_jax.densify.ops` grows and restarts them; other leaves are left alone).
    * ``accumulate(stats, view) -> stats``: inside the jitted step, once per rendered
      :class:`ViewRecord` (traced; gate on ``view.finite``).
    * ``due(step) -> bool``: whether :meth:`update` runs after ``step`` completed steps (host).
    * ``update(state, tx, step) -> (state, UpdateInfo)``: host side, between steps; may refill dead
      slots, clear ``alive`` bits or grow the capacity (through :mod:`cusgs_jax.densify.ops`).

    Optional hooks (the shell calls them for every strategy; the defaults do nothing):

    * :meth:`before_first_update`, :meth:`log_values`, :meth:`results`, :meth:`next_capacity`,
      :meth:`only_removes`.
    """

    name: str

    def init_state(self, capacity: int) -> Any: ...

    def accumulate(self, stats: Any, view: ViewRecord) -> Any: ...

    def due(self, step: int) -> bool: ...

    def update(self, state, tx, step: int) -> tuple[Any, UpdateInfo]: ...

    def before_first_update(self, probe: Probe) -> Mapping[str, Any]:
        """Called once per run, just before the strategy's first update (not again after a resume
        past it). Returns JSON values kept in the tally's ``values`` (default: nothing)."""
        del probe
        return {}

    def next_capacity(self, state, step: int) -> int | None:
        """The anchor capacity this strategy's next update is likely to grow ``state`` to (after ``step``
        completed steps), or None: the shell compiles the step for it in the background
        (:mod:`cusgs_jax.app.foresight`). A guess: a wrong one costs a compile, never a result."""
        del state, step
        return None

    def only_removes(self, step: int) -> bool:
        """Whether the update after ``step`` completed steps can only clear ``alive`` bits (no new anchors, no
        larger capacity): then no view needs more work after it, and the shell does not preview it to compile
        the step ahead (:mod:`cusgs_jax.app.foresight`). Default False (every update is previewed)."""
        del step
        return False

    def log_values(self, tally: Tally) -> Mapping[str, Any]:
        """Top-level keys this strategy adds to every ``metrics.jsonl`` row (default: none)."""
        del tally
        return {}

    def results(self, tally: Tally) -> Mapping[str, Any]:
        """Keys this strategy adds to ``eval.json``: one that is a field of
        :class:`~cusgs_jax.run_folder.EvalRecord` is set (a dict value merged into the run's dict of that key),
        any other goes under ``strategies`` (default: none)."""
        del tally
        return {}


def run_defaults(cfg: Config) -> tuple[dict, dict]:
    """``(row, result)``: the densification keys every run's ``metrics.jsonl`` rows and ``eval.json``
    hold whatever strategies it built (a strategy's :meth:`Strategy.log_values` /
    :meth:`Strategy.results` fill them in): ``pruned`` (feature-aware pruning's anchors, 0 without
    it), ``render_ms_before_prune`` (None without it) and the ``prune`` block of ``cfg.prune``."""
    prune = cfg.prune
    return (dict(pruned=0),
            dict(render_ms_before_prune=None,
                 prune=dict(strategy=prune.strategy, ratio=prune.ratio, lambda_norm=prune.lambda_norm,
                            lambda_grad=prune.lambda_grad, passes=0, pruned=0)))


def strategy_row(strategies, tallies: Mapping[str, Tally], cfg: Config) -> dict:
    """The densification keys of a ``metrics.jsonl`` row: :func:`run_defaults`, each strategy's
    ``log_values`` and ``densify`` ({strategy name: tally})."""
    row = run_defaults(cfg)[0]
    for strategy in strategies:
        row.update(strategy.log_values(tallies[strategy.name]))
    row["densify"] = {name: tally.as_dict() for name, tally in tallies.items()}
    return row


def strategy_results(strategies, tallies: Mapping[str, Tally], cfg: Config) -> dict:
    """The densification keys of ``eval.json``: :func:`run_defaults`, each strategy's ``results``
    (a dict value merged into the dict already there), ``densify`` ({strategy name: tally}) and
    ``strategies``: the keys a strategy adds that are no field of :class:`~cusgs_jax.run_folder.EvalRecord`
    ({key: value}; None when there are none)."""
    result, own = run_defaults(cfg)[1], {}
    fields = {f.name for f in dataclasses.fields(EvalRecord)}
    for strategy in strategies:
        for key, value in strategy.results(tallies[strategy.name]).items():
            into = result if key in fields else own
            merge = isinstance(value, dict) and isinstance(into.get(key), dict)
            into[key] = {**into[key], **value} if merge else value
    result["densify"] = {name: tally.as_dict() for name, tally in tallies.items()}
    result["strategies"] = own or None
    return result
