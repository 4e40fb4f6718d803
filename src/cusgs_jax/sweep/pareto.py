"""Multi-objective search over ``cusgs-train`` settings with Optuna (``experiment=pareto_search``).

The Hydra sweeper :class:`hydra_plugins.cusgs_pareto_sweeper.pareto_sweeper.ParetoSweeper`
(``hydra/sweeper=pareto``) is a thin shell around :class:`ParetoSearch`, which lives here so
that it can be read and tested without Hydra's plugin machinery.

Why not Hydra's own Optuna sweeper: hydra-optuna-sweeper 1.3.0 (its newest release) pins
``optuna<3``; with ``optuna>=4`` pip falls back to its 1.1.2, which builds its search space
from distributions that Optuna deprecated in 3.0 and removes in 6.0 and pins ``alembic<1.7``.
This module drives Optuna >= 4 directly with the same ask / launch / tell loop.

The loop (one *batch* of ``n_jobs`` trials at a time, like hydra-optuna-sweeper):

1. ``study.ask(search_space)`` ``n_jobs`` times (``study.enqueue_trial`` puts given points first);
2. each trial becomes one job's override list: its parameters (floats to 4 significant digits,
   the value the job actually runs) and the fixed command-line overrides;
3. the configured Hydra launcher (joblib, submitit, Ray, ...) runs the batch;
4. each job's return value — the objectives in ``objectives`` order, see
   :func:`objective_values` — is told to the study; a job that failed (it returns NaN, raised,
   or returned the wrong number of values) is told as ``TrialState.FAIL``;
5. ``pareto.json`` in the sweep folder is rewritten: every trial and the current front.

Search space syntax is Hydra's sweep grammar: ``interval(a, b)`` (float), ``tag(log, interval(a, b))``
(log-uniform float), ``range(a, b, step)`` (ints, or floats when any bound is a float; ``b``
excluded as in Python), ``choice(x, y, ...)`` or ``x,y,...`` (categorical). Anything else is a
fixed override passed to every job.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

__all__ = ["ParetoSearch", "SearchSpaceError", "check_sweeper_settings", "distributions_from_overrides", "objective_values",
           "result_objectives"]

DIRECTIONS = ("maximize", "minimize")


def check_sweeper_settings(sweeper: dict, arguments=()) -> str | None:
    """One line naming a bad ``hydra.sweeper.*`` setting of ``hydra/sweeper=pareto`` and its fix, or None.

    ``arguments``: the command line's overrides, whose sweeps join (and replace) ``params``, as
    :meth:`ParetoSweeper.sweep` builds the search space from both; every dimension is checked
    (:func:`distributions_from_overrides`) before any trial.
    """
    for key in ("n_trials", "n_jobs"):
        value = sweeper.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            return f"hydra.sweeper.{key}={value!r} must be a whole number >= 1, e.g. hydra.sweeper.{key}=8"
    objectives, directions = sweeper.get("objectives") or [], sweeper.get("directions") or []
    if not objectives or len(objectives) != len(directions):
        return (f"hydra.sweeper.objectives={list(objectives)} and hydra.sweeper.directions={list(directions)} "
                "need one direction per objective, e.g. objectives=[psnr,params] directions=[maximize,minimize]")
    bad = [d for d in directions if d not in DIRECTIONS]
    if bad:
        return f"hydra.sweeper.directions: {bad[0]!r} is not one of {list(DIRECTIONS)}"
    params = sweeper.get("params") or {}
    for key, value in params.items():
        if isinstance(value, dict):  # +hydra.sweeper.params.model.voxel_size=... nests a dict under "model"
            inner, example = key, value
            while isinstance(example, dict) and example:
                name, example = next(iter(example.items()))
                inner = f"{inner}.{name}"
            return (f"hydra.sweeper.params.{key} holds a group of options, not one search dimension (a dotted key "
                    f"after hydra.sweeper.params. on the command line nests them): give the dimension as its own "
                    f"override, e.g. '{inner}={example}', or as the key '{inner}' of hydra.sweeper.params in a "
                    "config file")
    try:
        distributions_from_overrides([f"{k}={v}" for k, v in params.items()] + list(arguments))
    except SearchSpaceError as error:
        return f"the search space of hydra/sweeper=pareto: {error}"
    except Exception as error:  # noqa: BLE001 - Hydra's parser and Optuna raise several types
        return f"hydra.sweeper.params: {str(error).splitlines()[0]}; use interval(a, b), tag(log, interval(a, b)), " \
               "range(a, b, step) or choice(x, y, ...)"
    return None


def result_objectives(result: dict, names) -> tuple[float, ...]:
    """The objectives ``names`` from a run's ``eval.json`` dict (``params`` is ``params.total``)."""
    values = []
    for name in names:
        value = result.get(name)
        if isinstance(value, dict):  # params: {"total": ..., parts...}
            value = value.get("total")
        values.append(float(value) if value is not None else math.nan)
    return tuple(values)


def objective_values(returned, n: int) -> list[float] | None:
    """``n`` finite floats from a job's return value, or None (the trial failed)."""
    if isinstance(returned, (list, tuple)):
        items = list(returned)
    elif n == 1:
        items = [returned]
    else:
        return None
    try:
        values = [float(v) for v in items]
    except (TypeError, ValueError):
        return None
    return values if len(values) == n and all(math.isfinite(v) for v in values) else None


def _distribution(override):
    """An Optuna distribution for a sweep override, or None for a fixed value."""
    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    value = override.value()
    if not override.is_sweep_override():
        return None
    if isinstance(value, ChoiceSweep):
        return CategoricalDistribution(list(value.list))
    log = "log" in (getattr(value, "tags", None) or set())
    line = override.input_line
    if isinstance(value, IntervalSweep):
        low, high = float(value.start), float(value.end)
        if not low <= high:
            flipped = f"interval({value.end}, {value.start})"
            return _bad_dimension(line, f"the interval runs from {value.start} down to {value.end}",
                                  f"{override.get_key_element()}={f'tag(log, {flipped})' if log else flipped}")
        if log and low <= 0:
            return _bad_dimension(line, f"a log interval needs a low end > 0, not {value.start}",
                                  f"{override.get_key_element()}=tag(log, interval({high / 100:g}, {value.end})) "
                                  f"or {override.get_key_element()}=interval({value.start}, {value.end})")
        return FloatDistribution(low, high, log=log)
    if isinstance(value, RangeSweep):
        start, stop, step = value.start, value.stop, value.step
        if not step > 0 or not stop - step >= start:
            return _bad_dimension(line, f"range({start}, {stop}, {step}) holds no value",
                                  "a start below the stop (which is excluded) and a step > 0, e.g. range(4, 12, 2)")
        if all(isinstance(x, int) for x in (start, stop, step)):
            if log and start <= 0:
                return _bad_dimension(line, f"a log range needs a start > 0, not {start}", "a start >= 1")
            return IntDistribution(start, stop - step, step=step, log=log)
        return FloatDistribution(float(start), float(stop) - float(step), step=float(step))
    raise ValueError(f"{override.input_line}: cannot turn {type(value).__name__} into a search dimension")


class SearchSpaceError(ValueError):
    """A sweep override that cannot be a search dimension; the message names it and the fix."""


def _bad_dimension(line: str, problem: str, fix: str):
    raise SearchSpaceError(f"{line}: {problem}; write {fix}")


def distributions_from_overrides(lines) -> tuple[dict, dict[str, str]]:
    """``(search space {key: distribution}, fixed {key: override line})`` from override strings.

    Later lines replace earlier ones for the same key (command line after config).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    space, fixed = {}, {}
    for override in OverridesParser.create().parse_overrides(list(lines)):
        key = override.get_key_element()
        space.pop(key, None)
        fixed.pop(key, None)
        distribution = _distribution(override)
        if distribution is None:
            fixed[key] = override.input_line
        else:
            space[key] = distribution
    return space, fixed


def _format(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class ParetoSearch:
    """Ask / launch / tell with an Optuna study of several objectives.

    Args:
        objectives: names of the values each job returns, e.g. ``["psnr", "params"]``.
        directions: ``"maximize"`` / ``"minimize"`` per objective.
        n_trials: trials in all (enqueued ones included).
        n_jobs: trials per batch handed to the launcher at once.
        sampler: an Optuna sampler (None: Optuna's default for several objectives).
        space: ``{key: optuna distribution}``; fixed: ``{key: "key=value"}`` passed to every job.
        enqueue: points ``{key: value}`` tried first (e.g. the hand-picked settings).
        out_dir: the sweep folder; ``pareto.json`` is written there after every batch.
    """

    def __init__(self, objectives, directions, n_trials, n_jobs, space, fixed=None, sampler=None,
                 enqueue=(), out_dir=None, study_name=None):
        import optuna

        if len(objectives) != len(directions):
            raise ValueError(f"{len(objectives)} objectives {list(objectives)} but {len(directions)} directions")
        self.objectives, self.directions = list(objectives), list(directions)
        self.n_trials, self.n_jobs = int(n_trials), max(1, int(n_jobs))
        self.space, self.fixed = dict(space), dict(fixed or {})
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.study = optuna.create_study(directions=self.directions, sampler=sampler, study_name=study_name)
        for point in enqueue or ():
            self.study.enqueue_trial(dict(point))
        self.jobs: dict[int, int] = {}  # trial number -> job number

    def overrides(self, trial) -> list[str]:
        """One job's override list: the trial's parameters, then the fixed overrides."""
        chosen = [f"{key}={_format(value)}" for key, value in trial.params.items()]
        return chosen + [line for key, line in self.fixed.items() if key not in trial.params]

    def run(self, launch, first_job: int = 0) -> list:
        """Run every trial; ``launch(list of override lists, first job number)`` returns JobReturns."""
        from optuna.trial import TrialState

        job = first_job
        while len(self.study.trials) < self.n_trials:
            batch = [self.study.ask(self.space) for _ in range(min(self.n_jobs, self.n_trials - len(self.study.trials)))]
            returns = launch([self.overrides(t) for t in batch], job)
            for trial, ret in zip(batch, returns):
                self.jobs[trial.number] = job
                job += 1
                try:
                    returned = ret.return_value
                except Exception:  # noqa: BLE001 - the job raised: Hydra re-raises it here
                    returned = None
                values = objective_values(returned, len(self.objectives))
                if values is None:
                    self.study.tell(trial, state=TrialState.FAIL)
                else:
                    self.study.tell(trial, values)
            self.write()
        return self.front()

    def front(self) -> list[dict]:
        """The non-dominated finished trials (Optuna's ``study.best_trials``) as :meth:`summary` rows."""
        return [self._row(t) for t in self.study.best_trials]

    def _row(self, trial) -> dict:
        values = dict(zip(self.objectives, trial.values)) if trial.values else None
        return {"trial": trial.number, "job": self.jobs.get(trial.number), "state": trial.state.name,
                "params": {k: _format(v) if isinstance(v, float) else v for k, v in trial.params.items()},
                "values": values}

    def summary(self) -> dict:
        """Everything ``pareto.json`` holds: the study set-up, every trial, the front's trial numbers."""
        return {"objectives": self.objectives, "directions": self.directions,
                "sampler": type(self.study.sampler).__name__,
                "search_space": {k: repr(d) for k, d in self.space.items()},
                "fixed": list(self.fixed.values()),
                "trials": [self._row(t) for t in self.study.trials],
                "front": [t.number for t in self.study.best_trials]}

    def write(self) -> Path | None:
        """(Re)write ``pareto.json`` in ``out_dir``."""
        if self.out_dir is None:
            return None
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path = self.out_dir / "pareto.json"
        path.write_text(json.dumps(self.summary(), indent=1))
        return path
