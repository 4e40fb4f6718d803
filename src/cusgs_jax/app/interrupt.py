"""Interruptions of a command-line run: Ctrl-C stops within seconds, SIGTERM checkpoints and stops.

``cusgs-train`` runs inside :func:`handling`. No handler raises: a signal only sets a flag, and the training loop
looks at it between steps (:func:`requested`), so nothing is interrupted inside XLA or inside a Python callback
that C++ called (an exception there aborts the process: "terminate called after throwing ...").

* **SIGINT** (Ctrl-C): the loop stops after the step under way and the command exits 130 with one line; a run
  that is not stepping (loading, compiling) is stopped by a watcher after :data:`INTERRUPT_GRACE_S` — background
  compiles are abandoned, never waited for. A second Ctrl-C changes nothing. The newest checkpoint resumes
  (``train.resume=true``).
* **SIGTERM** (what SLURM sends before a preemption or a time limit): the loop writes a checkpoint at the step it
  reached and the command exits 143 with one line; ``train.resume=true`` continues from there. A run that does not
  reach a step boundary within :data:`TERMINATE_GRACE_S` exits without one (its newest checkpoint stands).

Python's C-level handler writes each signal to a wakeup pipe at once (:func:`signal.set_wakeup_fd`), even while
the main thread waits in C++; a watcher thread reads it and enforces the grace periods. pycolmap installs glog's
failure-signal handler for SIGTERM when it is imported (it printed a 30-line C++ stack dump); :func:`handling`
imports it first, so the handler installed after it is the one that stays.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import threading
import time

__all__ = ["handling", "requested", "Interrupted", "INTERRUPT_GRACE_S", "TERMINATE_GRACE_S"]

INTERRUPT_GRACE_S = 1.5  # Ctrl-C: seconds the run has to stop by itself before the watcher ends the process
TERMINATE_GRACE_S = 20.0  # SIGTERM: seconds to reach a step boundary and checkpoint (SLURM's KillWait is 30 s)
EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}

_pending: list[int] = []  # the signals received, in order (empty: none)


class Interrupted(Exception):
    """The run stopped for a signal at a step boundary (``signum``; ``step``: completed steps, checkpointed for
    SIGTERM)."""

    def __init__(self, signum: int, step: int, checkpoint: str | None):
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        what = "interrupted (Ctrl-C)" if signum == signal.SIGINT else "terminated (SIGTERM)"
        saved = f"; checkpoint of step {step} in {checkpoint}" if checkpoint else ""
        super().__init__(f"{what} after step {step}{saved}: continue with train.resume=true")

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.signum, 1)


def requested() -> int | None:
    """The first signal received while :func:`handling` is active (``signal.SIGINT`` / ``SIGTERM``), or None."""
    return _pending[0] if _pending else None


def _watch(read_fd: int, prog: str, done: threading.Event) -> None:
    """The watcher thread: end the process when a signal's grace period passes and the run has not stopped."""
    deadline, signum = None, None
    while not done.is_set():
        timeout = None if deadline is None else max(deadline - time.monotonic(), 0.0)
        if timeout is not None and timeout == 0.0:
            line = ("interrupted (Ctrl-C) before a step ended" if signum == signal.SIGINT
                    else "terminated (SIGTERM) before a step ended: no new checkpoint")
            print(f"{prog}: {line}; the newest checkpoint resumes with train.resume=true", file=sys.stderr, flush=True)
            os._exit(EXIT_CODES[signum])
        ready, _, _ = select.select([read_fd], [], [], timeout if timeout is not None else 0.5)
        if not ready:
            continue
        try:
            data = os.read(read_fd, 64)
        except OSError:
            return
        for byte in data:
            if byte in EXIT_CODES and signum is None:
                signum = byte
                deadline = time.monotonic() + (INTERRUPT_GRACE_S if byte == signal.SIGINT else TERMINATE_GRACE_S)


@contextlib.contextmanager
def handling(prog: str = "cusgs-train"):
    """Inside: SIGINT and SIGTERM stop the run as the module docstring says (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _pending.clear()
    try:  # its import installs glog's failure-signal handler for SIGTERM: before ours, not over it
        import pycolmap  # noqa: F401
    except ImportError:
        pass
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous = {sig: signal.getsignal(sig) for sig in EXIT_CODES}
    old_wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

    def flag(signum, frame):  # never raises (see the module docstring)
        del frame
        if signum not in _pending:
            _pending.append(signum)

    for sig in EXIT_CODES:
        signal.signal(sig, flag)
    done = threading.Event()
    watcher = threading.Thread(target=_watch, args=(read_fd, prog, done), name="cusgs-interrupt", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        signal.set_wakeup_fd(old_wakeup)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        watcher.join(timeout=1.0)
        os.close(read_fd)
        os.close(write_fd)
        _pending.clear()
