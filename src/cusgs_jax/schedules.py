"""Schedules that never run: a densification, evaluation or checkpoint schedule of a :class:`~cusgs_jax.config.Config`
that does nothing within ``train.iterations`` is named with a value that would run (a run warns once per setting;
``cusgs-train -m`` warns about a sweep over such a setting before any job starts, :mod:`cusgs_jax.app.overrides`)."""

from __future__ import annotations

import logging
from typing import Optional

from cusgs_jax.config import Config

__all__ = ["idle_schedules", "schedule_warnings", "warn_schedules"]


def _first_due(start: int, stop: int, interval: int, iterations: int) -> Optional[int]:
    """The first step ``s`` in ``1..iterations`` with ``start <= s <= stop`` and ``s % interval == 0`` (the
    densification schedules, densify/scaffold.py and densify/feature_prune.py), or None."""
    first = -(-max(start, 1) // interval) * interval
    return first if first <= min(stop, iterations) else None


def _schedule_warning(name: str, what: str, start: int, stop: int, interval: int, iterations: int) -> Optional[str]:
    """The warning for the densification schedule ``name`` (``grow``, ``prune``) that runs no update, or None: it
    names the setting at fault and values that would run (the first of a few changes that :func:`_first_due` runs)."""
    if _first_due(start, stop, interval, iterations) is not None:
        return None
    at = max(interval, iterations // 6 // interval * interval)  # about a sixth into the run, as 500 of 3000
    half = max(1, iterations // 2)
    if start > iterations:
        why = f"{name}.start={start} is past train.iterations={iterations}"
    elif stop < max(start, 1):
        why = f"{name}.stop={stop} is before {name}.start={start}" if stop < start else f"{name}.stop={stop} < 1"
    else:
        why = (f"no multiple of {name}.interval={interval} falls in [{name}.start={start}, "
               f"min({name}.stop={stop}, train.iterations={iterations})]")
    for change in (dict(start=at), dict(stop=max(start, iterations)), dict(interval=max(start, 1)),
                   dict(start=at, stop=max(at, stop)), dict(start=half, stop=max(half, stop), interval=half)):
        settings = dict(dict(start=start, stop=stop, interval=interval), **change)
        if _first_due(settings["start"], settings["stop"], settings["interval"], iterations) is not None:
            break
    current = dict(start=start, stop=stop, interval=interval)
    return f"{why}: {what} runs; e.g. " + " ".join(f"{name}.{key}={value}" for key, value in change.items()
                                                   if value != current[key])


def idle_schedules(cfg: Config) -> dict[str, str]:
    """The schedules of ``cfg`` that never run within ``train.iterations``: {what they schedule: a warning naming
    the setting and a value that would run}. Keys: ``prune`` (feature-aware pruning passes, with
    ``prune.strategy=feature_aware``: ``prune.start`` / ``stop`` / ``interval``), ``grow`` (growing steps:
    ``grow.start`` / ``stop`` / ``interval``), ``eval.every`` (past the end: the held-out curve holds only its final
    point) and ``train.checkpoint_every`` (at or past the end: no checkpoint before the final one)."""
    iterations, idle = cfg.train.iterations, {}
    if cfg.prune.strategy == "feature_aware":
        p = cfg.prune
        idle["prune"] = _schedule_warning("prune", "no pruning pass", p.start, p.stop, p.interval, iterations)
    g = cfg.grow
    idle["grow"] = _schedule_warning("grow", "no growing (nor Scaffold-GS opacity pruning) step", g.start, g.stop,
                                     g.interval, iterations)
    if cfg.eval.every and cfg.eval.every > iterations:
        idle["eval.every"] = (f"eval.every={cfg.eval.every} is past train.iterations={iterations}: the held-out curve "
                              f"gets only its final point; e.g. eval.every={max(1, iterations // 10)}")
    if cfg.train.checkpoint_every and cfg.train.checkpoint_every >= iterations:
        idle["train.checkpoint_every"] = (
            f"train.checkpoint_every={cfg.train.checkpoint_every} is not before train.iterations={iterations}: no "
            f"checkpoint before the final one (a killed run restarts from step 0); e.g. "
            f"train.checkpoint_every={max(1, iterations // 3)}")
    return {key: line for key, line in idle.items() if line}


def schedule_warnings(cfg: Config) -> list[str]:
    """One line per schedule of ``cfg`` that never runs within ``train.iterations`` (:func:`idle_schedules`),
    naming the setting and a value that would run: a sweep over it, or over what it schedules, would mean
    nothing. :func:`warn_schedules` logs them."""
    return list(idle_schedules(cfg).values())


def warn_schedules(cfg: Config) -> list[str]:
    """Log each :func:`schedule_warnings` line as a warning (``cusgs_jax`` logger); returns them."""
    warnings = schedule_warnings(cfg)
    for line in warnings:
        logging.getLogger("cusgs_jax").warning("%s", line)
    return warnings
