"""Programs compiled ahead of their first call, off the training loop's path.

A jitted function's program is fixed by the shapes, dtypes and shardings of its arguments; the
run knows them before the call that would compile it (the first step's once the state and the
first batch exist, the next anchor capacity's before a growth makes it). :meth:`Program.prepare`
lowers and compiles the program for such arguments on a background thread (JAX's
ahead-of-time API, ``jax.jit(f).lower(*types).compile()``; XLA's compile runs in C++ without the
interpreter lock, so the loop goes on), and the call with arguments of those types runs the ready
executable. The executable is the one the jitted call would have built — the same function, the
same argument types — so the numbers are the same; should it still refuse the arguments (a
``TypeError`` raised before anything runs or is donated), the jitted function is called and
compiles as before. Nothing is ever run by the wrong program.

The run waits for a program only when it calls one whose compile has not finished: the wait is
reported to ``on_wait`` (the run's ``compile_wait``, :class:`cusgs_jax.app.budget.TimeBudget`).
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import threading
import time
from collections.abc import Callable

import jax

log = logging.getLogger("cusgs_jax")

WORKERS = 2  # compiles at once by default: the start's step and evaluation render side by side
THREAD_PREFIX = "cusgs-compile-ahead"  # the background thread's name (CompileLog tells its compiles apart by it)
#: A test hook: seconds every background compile waits before it starts (a machine whose compiles are late).
DELAY_ENV = "CUSGS_TEST_COMPILE_DELAY_S"


def in_background() -> bool:
    """Whether the calling thread is a :class:`Ahead` compile thread."""
    return threading.current_thread().name.startswith(THREAD_PREFIX)


def spec(x):
    """One argument leaf as ahead-of-time lowering takes it: a ``jax.ShapeDtypeStruct`` with the array's
    shape, dtype, weak type and (committed arrays only) sharding; other leaves as they are."""
    if isinstance(x, jax.Array):
        sharding = x.sharding if getattr(x, "committed", False) else None
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=x.weak_type)
    return x


def specs(tree):
    """:func:`spec` of every leaf of ``tree`` (taken on the calling thread: its arrays may be donated later)."""
    return jax.tree_util.tree_map(spec, tree)


def signature(args) -> tuple:
    """What decides a jitted function's program for ``args``: the tree structure (static fields
    included) and every leaf's shape, dtype and weak type (a Python scalar by its type, not its value)."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    # dtype objects, not their names (a name is built anew at every call): this runs at every step
    return treedef, tuple((tuple(x.shape), x.dtype, bool(getattr(x, "weak_type", False)))
                          if hasattr(x, "shape") and hasattr(x, "dtype") else type(x).__name__ for x in leaves)


class Ahead:
    """Background compile threads for a run (``with Ahead(on_wait) as ahead:``): up to ``workers`` compiles at
    once (XLA compiles a program mostly on one core), until :meth:`settle` says otherwise.

    Args:
      on_wait: told the seconds of every wait for a program still compiling.
      enabled: False compiles nothing ahead (every program compiles on its first call, as a plain jit).
      workers: compile threads (default :data:`WORKERS`).
      delay_s: seconds each background compile waits before it starts (a test hook for late programs; default
        the environment's :data:`DELAY_ENV`, else 0). Settable between compiles.
    """

    def __init__(self, on_wait: Callable[[float], None] | None = None, enabled: bool = True,
                 workers: int | None = None, delay_s: float | None = None):
        self.enabled = enabled
        self.delay_s = float(os.environ.get(DELAY_ENV, 0.0) if delay_s is None else delay_s)
        self._closing = threading.Event()  # set by close: a delayed compile gives up its wait
        self.workers = max(1, default_workers() if workers is None else int(workers))
        self._pool = _pool(self.workers)
        self._on_wait = on_wait or (lambda seconds: None)
        self.submitted = 0  # programs compiled ahead
        self.waits = 0  # calls that waited for one
        self.compile_seconds: list[float] = []  # wall seconds of each finished background compile
        self._futures: list[concurrent.futures.Future] = []  # compiles submitted and not yet seen done (settle)

    def compile(self, fn: Callable, args) -> concurrent.futures.Future:
        """A future of ``fn``'s executable for the types of ``args`` (arrays or ``ShapeDtypeStruct`` s).

        ``fn`` is a jitted function, or one that places its inputs before calling ``fn.jitted``
        (``fn.types(*args)`` gives the placed types).
        """
        jitted = getattr(fn, "jitted", fn)
        types = specs(tuple(args))
        if hasattr(fn, "types"):
            types = fn.types(*types)
        self.submitted += 1

        delay = self.delay_s

        def lower_and_compile():
            start = time.perf_counter()
            compiled = jitted.lower(*types).compile()
            self.compile_seconds.append(time.perf_counter() - start)
            return compiled

        def compile_now():
            if delay > 0 and self._closing.wait(delay):
                raise RuntimeError("the run ended before this delayed compile started")
            return lower_and_compile()

        future = self._pool.submit(compile_now)
        future.in_foreground = lower_and_compile  # what result() runs when the caller needs it before it started
        self._futures = [f for f in self._futures if not f.done()] + [future]
        return future

    def settle(self, workers: int | None = None) -> None:
        """Wait for every compile submitted so far (the wait reported as one), then compile on ``workers`` threads
        (None: as before): where a compile would share the cores with the steps (a CPU backend), the loop starts
        after the start-up's programs, not beside them, and later compiles take one core at a time."""
        pending = [future for future in self._futures if not future.done()]
        if pending:
            start = time.perf_counter()
            concurrent.futures.wait(pending)
            self.waits += 1
            self._on_wait(time.perf_counter() - start)
        self._futures = []
        if workers is not None and workers != self.workers:
            self._pool.shutdown(wait=True)  # idle: everything it was given is done
            self.workers, self._pool = workers, _pool(workers)

    def loop_starts(self) -> None:
        """The training loop starts stepping: the compile policy for the steps' time. On a CPU backend a compile
        shares the steps' cores: the loop starts after the start-up's programs (waited for here, one wait), and
        later compiles take one core at a time. On an accelerator the host's cores are idle while the device
        trains: the pool stays as it is."""
        if jax.default_backend() == "cpu":
            self.settle(workers=1)

    def result(self, future: concurrent.futures.Future):
        """The executable of ``future`` (waiting, and reporting the wait, if it is not ready), or None when its
        compile failed (the jitted call then compiles, and raises, on the caller's path).

        A compile still queued behind others (the foresight's speculative ones) is taken out of the queue and
        compiled here, now: the caller waits for its own program only, not for those queued before it (the
        compile log charges it to ``compile_wait`` as a compile on the caller's thread)."""
        foreground = getattr(future, "in_foreground", None)
        if not future.done() and foreground is not None and future.cancel():
            self.waits += 1
            try:
                return foreground()
            except Exception as error:  # noqa: BLE001
                log.debug("compiling failed (%s): the call compiles the program itself", error)
                return None
        if not future.done():
            start = time.perf_counter()
            concurrent.futures.wait([future])
            self.waits += 1
            self._on_wait(time.perf_counter() - start)
        try:
            return future.result()
        except Exception as error:  # noqa: BLE001
            log.debug("compiling ahead failed (%s): the call compiles the program itself", error)
            return None

    def close(self) -> None:
        """Drop what was not started; wait for a compile under way (XLA cannot interrupt it)."""
        self._closing.set()
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Ahead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def default_workers(backend: str | None = None, cpus: int | None = None) -> int:
    """Compiles at once: :data:`WORKERS` on a CPU backend (the start's step and render side by side; the loop
    narrows it to one, :meth:`Ahead.loop_starts`); on an accelerator, whose host cores are idle while the device
    trains, one per four host cores, from :data:`WORKERS` to 4 (XLA compiles a program mostly on one core)."""
    backend = jax.default_backend() if backend is None else backend
    if backend == "cpu":
        return WORKERS
    cpus = (os.cpu_count() or 1) if cpus is None else cpus
    return max(WORKERS, min(4, cpus // 4))


def _pool(workers: int) -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix=THREAD_PREFIX)


class Program:
    """A jitted function with executables compiled ahead for the argument types it will be called with.

    ``program(*args)`` runs the executable prepared for the types of ``args`` (waiting for its compile if
    it is under way), else the jitted function. A function that places its inputs before its jitted call
    (the batched step: ``fn.place(*args)``, ``fn.types(*args)``, ``fn.jitted``) is compiled for the placed
    types and its executable called with the placed inputs.

    Attributes:
      jitted: the function as built; fallbacks: calls an executable refused (run by ``jitted``).
    """

    def __init__(self, jitted: Callable, ahead: Ahead | None = None):
        self.jitted, self.ahead = jitted, ahead
        self._ready: dict[tuple, object] = {}  # signature -> Compiled (None: refused once, use jitted)
        self._pending: dict[tuple, concurrent.futures.Future] = {}
        self._called: set[tuple] = set()  # signatures the jitted function compiled on a call (jit's own cache)
        self.fallbacks = 0

    def prepare(self, *args) -> bool:
        """Start compiling the program for the types of ``args`` (arrays or ``ShapeDtypeStruct`` s) unless it is
        ready or under way; returns whether a compile was started."""
        if self.ahead is None or not self.ahead.enabled:
            return False
        key = signature(args)
        if key in self._ready or key in self._pending:
            return False
        self._pending[key] = self.ahead.compile(self.jitted, args)
        return True

    def ready(self, *args) -> bool:
        """Whether a call with arguments of these types runs without waiting for a compile: its executable was
        compiled ahead (or by an earlier call). Always true when nothing is compiled in the background (a call
        then compiles on the caller's path: there is nothing to wait for but the call)."""
        if self.ahead is None or not self.ahead.enabled:
            return True
        key = signature(args)
        if key in self._ready or key in self._called:
            return True
        future = self._pending.get(key)
        return future is not None and future.done()

    def wait(self, *args) -> None:
        """Wait for the program prepared for the types of ``args`` (if one is being compiled)."""
        self._resolve(signature(args))

    def _resolve(self, key: tuple) -> None:
        if key in self._pending:
            self._ready[key] = self.ahead.result(self._pending.pop(key))

    def __call__(self, *args):
        if self.ahead is None or not self.ahead.enabled:
            return self.jitted(*args)
        key = signature(args)
        self._resolve(key)
        compiled = self._ready.get(key)
        if compiled is not None:
            place = getattr(self.jitted, "place", None)
            try:
                return compiled(*(place(*args) if place else args))
            except (TypeError, ValueError) as error:  # argument types or shardings refused before anything ran
                log.debug("an ahead-compiled program refused its arguments (%s): the jitted function compiles", error)
                self._ready[key], self.fallbacks = None, self.fallbacks + 1
        self._called.add(key)
        return self.jitted(*args)

    def __getattr__(self, name):  # e.g. the batched step's ``mesh``
        if name.startswith("_") or name == "jitted":
            raise AttributeError(name)
        return getattr(self.jitted, name)
