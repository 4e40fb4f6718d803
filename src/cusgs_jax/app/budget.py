"""Where a run's wall time goes: ``eval.json``'s ``time``, the closing log line, ``cusgs-report``'s tables.

A :class:`TimeBudget` charges the wall time since it started to one stage at a time
(``with budget.stage("evaluation"): ...``; nested stages charge the inner one), and moves the
seconds the run stood still for a compiler out of the stage they happened in into ``compile_wait``:
compiles on the calling thread (the :class:`~cusgs_jax.app.compiles.CompileLog`'s foreground
seconds) and waits for a program the compile-ahead thread had not finished (:meth:`TimeBudget.waited`,
:mod:`cusgs_jax.app.ahead`). Time outside every stage is ``other``. The stages, ``compile_wait``
and ``other`` therefore add up to ``total`` by construction; ``total`` is then compared with the
process wall outside (the README's main job: within 5 %). ``compile`` is every compile second,
those of the background thread included (which overlap the stages): not a part of the sum.
"""

from __future__ import annotations

import contextlib
import time

from cusgs_jax.app.clock import Clock
from cusgs_jax.app.compiles import CompileLog

#: The stages, in the order a run passes them (``eval.json``'s ``time`` keys, with ``compile_wait``, ``other``,
#: ``total`` and ``compile``).
STAGES = ("startup", "load", "features", "psc", "init", "probe", "train_steps", "densify", "evaluation",
          "checkpoints", "report")


class TimeBudget:
    """Seconds per stage of one process's run, and its training clock.

    Args:
      compiles: the run's compile log, entered (its seconds move into ``compile``); None: compiles are not
        told apart (``compile_wait`` holds only waits for background compiles, ``compile`` is None).
      start: ``time.perf_counter()`` at which the budget starts (default now); the time until the
        first stage is ``startup`` when given (e.g. the process's import of the package).

    Attributes:
      clock: the run's training clock (:class:`~cusgs_jax.app.clock.Clock`: ``metrics.jsonl``'s and the curve's
        ``wall_s``, ``eval.json``'s ``train_wall_s``); a resumed run sets it to the checkpoint's (:meth:`resume_clock`).
    """

    def __init__(self, compiles: CompileLog | None = None, start: float | None = None):
        self.compiles = compiles
        self.clock = Clock()
        self.seconds = {name: 0.0 for name in STAGES}
        self.seconds.update(compile_wait=0.0, other=0.0)
        now = time.perf_counter()
        self._since = now if start is None else start
        self._compiled = self._foreground()
        self._waited = 0.0  # waits for background compiles not yet charged
        self._current = "other" if start is None else "startup"
        self._start = self._since

    def _foreground(self) -> float:
        return 0.0 if self.compiles is None else self.compiles.foreground_seconds

    def resume_clock(self, seconds: float) -> None:
        """Continue the training clock from ``seconds`` (a resumed run: the checkpoint's ``wall_s``)."""
        self.clock = Clock(float(seconds))

    def _charge(self) -> None:
        now, compiled = time.perf_counter(), self._foreground()
        wait_part = compiled - self._compiled + self._waited
        self.seconds[self._current] += (now - self._since) - wait_part
        self.seconds["compile_wait"] += wait_part
        self._since, self._compiled, self._waited = now, compiled, 0.0

    def waited(self, seconds: float) -> None:
        """``seconds`` just spent waiting for a program compiled on the background thread: ``compile_wait``."""
        self._waited += seconds

    @contextlib.contextmanager
    def stage(self, name: str):
        """Charge the time inside to ``name`` (one of :data:`STAGES`), less its compilation."""
        if name not in self.seconds:
            raise KeyError(f"unknown stage {name!r}; stages: {STAGES}")
        self._charge()
        outer, self._current = self._current, name
        try:
            yield
        finally:
            self._charge()
            self._current = outer

    def begin(self, name: str) -> None:
        """Charge from now on to ``name`` until the next :meth:`begin` or stage (for the startup → run handover)."""
        self._charge()
        self._current = name

    def as_dict(self) -> dict:
        """{stage: seconds, "compile_wait", "other", "total", "compile"} (rounded to ms); all but ``compile``
        add up to ``total``."""
        self._charge()
        out = {name: round(value, 3) for name, value in self.seconds.items()}
        out["total"] = round(time.perf_counter() - self._start, 3)
        out["compile"] = None if self.compiles is None else round(self.compiles.seconds, 3)
        return out

    def line(self) -> str:
        """One log line: the stages that took time, largest first (``compile`` last: it overlaps them)."""
        table = self.as_dict()
        total, compiled = table.pop("total"), table.pop("compile")
        parts = [f"{name} {value:.1f}" for name, value in sorted(table.items(), key=lambda kv: -kv[1]) if value >= 0.05]
        return (f"time {total:.1f} s: " + ", ".join(parts)
                + ("" if compiled is None else f" (compiling {compiled:.1f} s in all)"))
