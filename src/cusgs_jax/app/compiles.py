"""Every XLA compilation of a run: how many, their seconds, which function (JAX's public monitoring events).

JAX reports each compilation through :mod:`jax.monitoring`: tracing to a jaxpr
(``/jax/core/compile/jaxpr_trace_duration``), lowering to MLIR
(``/jax/core/compile/jaxpr_to_mlir_module_duration``) and the backend compile
(``/jax/core/compile/backend_compile_duration``), the last two with the function's name; a program
found in the persistent compilation cache (:mod:`cusgs_jax.app.xla_cache`) fires
``/jax/compilation_cache/cache_hits`` inside its backend "compile", which then only loads it.

:class:`CompileLog` listens while it is entered and keeps one record per backend compile:
``{"function", "seconds" (trace + lower + compile or load), "cached", "background"}``; a compile on
the compile-ahead thread (:mod:`cusgs_jax.app.ahead`) is ``background``: nothing waited for it there.
"""

from __future__ import annotations

import collections
import threading

import jax.monitoring

from cusgs_jax.app.ahead import in_background

TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
LOWER_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
BACKEND_EVENT = "/jax/core/compile/backend_compile_duration"
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"


def compiled_name(function) -> str:
    """The name JAX's compile events give a jitted ``function`` (``jit(<its Python name>)``); a wrapper that
    holds one as ``jitted`` (:class:`~cusgs_jax.app.ahead.Program`, the batched step) names its function."""
    while "jitted" in getattr(function, "__dict__", {}):
        function = function.jitted
    return f"jit({function.__name__})"


class CompileLog:
    """``with CompileLog() as log:`` records every compilation of this process while inside.

    Attributes:
      records: one dict per backend compilation, in order: ``function`` (e.g. ``jit(step)``),
        ``seconds`` (its tracing, lowering and compiling — or loading from the persistent cache)
        and ``cached`` (loaded from the persistent cache, not compiled).
      seconds: all compilation seconds so far (tracing and lowering included, also of functions whose
        backend compile was skipped because jit's in-memory cache had the program).
      backend_seconds: the backend's part of ``seconds`` (compiling, or loading from the persistent
        cache): what the persistent cache saves; tracing and lowering happen in every process.
      foreground_seconds: the part of ``seconds`` spent on threads other than the compile-ahead one
        (the calling thread stood still for them).
    """

    def __init__(self):
        self.records: list[dict] = []
        self.seconds = 0.0
        self.backend_seconds = 0.0
        self.foreground_seconds = 0.0
        self._pending: dict[int, float] = {}  # per thread: tracing / lowering seconds not yet attributed
        self._hits: dict[int, int] = {}  # per thread: persistent-cache hits inside the backend compile under way
        self._lock = threading.Lock()

    def _on_duration(self, event: str, duration: float, **kwargs) -> None:
        if event not in (TRACE_EVENT, LOWER_EVENT, BACKEND_EVENT):
            return
        thread, background = threading.get_ident(), in_background()
        with self._lock:
            self.seconds += duration
            if not background:
                self.foreground_seconds += duration
            if event != BACKEND_EVENT:
                self._pending[thread] = self._pending.get(thread, 0.0) + duration
                return
            self.backend_seconds += duration
            self.records.append(dict(function=str(kwargs.get("fun_name", "?")),
                                     seconds=round(duration + self._pending.pop(thread, 0.0), 4),
                                     backend_seconds=round(duration, 4), cached=self._hits.pop(thread, 0) > 0,
                                     background=background))

    def _on_event(self, event: str, **kwargs) -> None:
        if event == CACHE_HIT_EVENT:
            with self._lock:
                thread = threading.get_ident()
                self._hits[thread] = self._hits.get(thread, 0) + 1

    def __enter__(self) -> CompileLog:
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)
        jax.monitoring.register_event_listener(self._on_event)
        return self

    def __exit__(self, *exc) -> None:
        jax.monitoring.unregister_event_duration_listener(self._on_duration)
        jax.monitoring.unregister_event_listener(self._on_event)

    def count(self, function=None) -> int:
        """Backend compilations (cache loads included) of ``function`` — the jitted function itself (or a
        :class:`~cusgs_jax.app.ahead.Program` of it: :func:`compiled_name`), or its name such as ``jit(step)`` —
        or of all."""
        name = function if function is None or isinstance(function, str) else compiled_name(function)
        return sum(1 for r in self.records if name is None or r["function"] == name)

    def summary(self, top: int = 8) -> dict:
        """``eval.json``'s ``compilations``: {"count", "compiled", "from_cache", "ahead" (on the compile-ahead
        thread), "seconds", "backend_seconds", "foreground_seconds",
        "functions": {name: {"count", "seconds"}} for the ``top`` most expensive names, the rest as "other"}."""
        by_name: dict[str, list] = collections.defaultdict(lambda: [0, 0.0])
        for record in self.records:
            by_name[record["function"]][0] += 1
            by_name[record["function"]][1] += record["seconds"]
        ranked = sorted(by_name.items(), key=lambda item: -item[1][1])
        functions = {name: dict(count=n, seconds=round(s, 3)) for name, (n, s) in ranked[:top]}
        rest = ranked[top:]
        if rest:
            functions["other"] = dict(count=sum(n for _, (n, _) in rest), seconds=round(sum(s for _, (_, s) in rest), 3))
        cached = sum(1 for r in self.records if r["cached"])
        return dict(count=len(self.records), compiled=len(self.records) - cached, from_cache=cached,
                    ahead=sum(1 for r in self.records if r.get("background")),
                    seconds=round(self.seconds, 3), backend_seconds=round(self.backend_seconds, 3),
                    foreground_seconds=round(self.foreground_seconds, 3), functions=functions)
