"""Orbax's noise after a failed checkpoint save or read, caught or dropped (:mod:`.checkpoint`).

When one array of a save fails, orbax repeats the failure from its abandoned threads: ``absl``
and ``asyncio`` log records, unraisable "Event loop is closed" errors, TensorStore's printed
tracebacks. :class:`_OrbaxLogCapture` collects orbax's own log lines around one call;
:func:`quiet_orbax` drops the repetition while an application's block runs (the library itself
changes no process-wide hook). :func:`_os_error` finds the OS error behind a failure.
"""

from __future__ import annotations

import contextlib
import errno
import gc
import logging
import os
import re
import sys
import warnings

__all__ = ["quiet_orbax"]

_DISK_FULL = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota exceeded"}


@contextlib.contextmanager
def quiet_orbax():
    """Drop the noise orbax leaves behind after a failed save or read, while the block runs.

    The failure itself still arrives as one :class:`~cusgs_jax.errors.CheckpointError`
    (or one warning line); what this drops is the repetition that orbax's
    abandoned threads print afterwards: ``absl`` and ``asyncio`` log records
    naming the failed checkpoint folder, unraisable "Event loop is closed"
    errors and "coroutine ... was never awaited" warnings. Everything else
    passes. On exit the ``absl``/``asyncio`` filters, ``sys.unraisablehook`` and
    ``warnings.filters`` are as they were. Nests; not meant for concurrent use
    from several threads (it changes process-wide hooks while active).
    """
    with warnings.catch_warnings():
        _AFTERMATH.install()
        try:
            yield
        finally:
            # an abandoned asyncio task reports its exception when it is collected: collect now, while the
            # filters hold, rather than at some later collection after they are gone
            gc.collect()
            _AFTERMATH.uninstall()


def _chain(error: BaseException):
    """``error`` and every exception linked to it (causes, contexts, exception-group members)."""
    seen, todo = set(), [error]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        yield e
        todo.extend(getattr(e, "exceptions", None) or ())
        todo.extend((e.__cause__, e.__context__))


_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")


def _os_error(error: BaseException) -> tuple[int | None, str] | None:
    """``(errno, reason)`` of the OS error behind ``error``, or None if it is not one.

    Python-side writes raise :class:`OSError`; TensorStore's raise ``ValueError``
    with ``[os_error_code='28']`` and the ``strerror`` text in the message.
    """
    found = None
    for e in _chain(error):
        if isinstance(e, OSError):
            code = e.errno
            reason = e.strerror or str(e)
        else:
            text = str(e)
            match = _OS_ERROR_CODE.search(text)
            code = int(match.group(1)) if match else next(
                (c for c in _DISK_FULL if os.strerror(c) in text), None)
            if code is None:
                continue
            reason = os.strerror(code)
        if code in _DISK_FULL:
            return code, reason
        found = found or (code, reason)
    return found


class _OrbaxLogCapture(logging.Filter):
    """Hold back orbax's warnings/errors (it logs through ``absl``) while active.

    :meth:`replay` passes them on; records not replayed are dropped, which is
    what happens when the failure they describe becomes one clear
    :class:`CheckpointError` or warning line instead.
    """

    def __init__(self):
        super().__init__()
        self.records: list[logging.LogRecord] = []
        self.logger = logging.getLogger("absl")

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.records.append(record)
            return False
        return True

    def __enter__(self):
        self.logger.addFilter(self)
        return self

    def __exit__(self, *exc):
        self.logger.removeFilter(self)
        return False

    def replay(self) -> None:
        self.logger.removeFilter(self)
        records, self.records = self.records, []
        for record in records:
            self.logger.handle(record)


class _Aftermath(logging.Filter):
    """Drop the noise orbax leaves behind after a failure that was already reported as one line.

    When one array fails, orbax stops waiting for the others: their threads log
    the same error again (``absl``), their futures report "exception was never
    retrieved" (``asyncio``), and TensorStore calls back into closed event loops
    (unraisable "Event loop is closed"), possibly long after the call returned.
    While installed by :func:`quiet_orbax`, once :meth:`mute` named a folder,
    records and unraisable exceptions that mention it, or that are such asyncio
    leftovers of an OS error, are dropped; everything else passes.
    """

    def __init__(self):
        super().__init__()
        self.paths: set[str] = set()
        self.previous_hook = self.previous_excepthook = None
        self.depth = 0

    def mute(self, prefix: str) -> None:
        """While installed (inside :func:`quiet_orbax`), drop from now on what mentions ``prefix``."""
        if self.depth == 0:
            return
        self.paths.add(prefix)
        # the writes or reads orbax abandoned are garbage-collected unawaited (quiet_orbax restores the filters)
        warnings.filterwarnings("ignore", r"coroutine '.*' was never awaited", RuntimeWarning)

    def install(self) -> None:
        self.depth += 1
        if self.depth > 1:
            return
        logging.getLogger("absl").addFilter(self)
        logging.getLogger("asyncio").addFilter(self)
        self.previous_hook = sys.unraisablehook
        sys.unraisablehook = self.unraisable
        # TensorStore reports an exception raised in its Python callbacks with PyErr_Print, which
        # goes through sys.excepthook: "Event loop is closed" from a loop orbax already closed.
        self.previous_excepthook = sys.excepthook
        sys.excepthook = self.excepthook

    def uninstall(self) -> None:
        self.depth -= 1
        if self.depth > 0:
            return
        logging.getLogger("absl").removeFilter(self)
        logging.getLogger("asyncio").removeFilter(self)
        if sys.unraisablehook == self.unraisable:
            sys.unraisablehook = self.previous_hook
        if sys.excepthook == self.excepthook:
            sys.excepthook = self.previous_excepthook
        self.previous_hook = self.previous_excepthook = None
        self.paths.clear()

    def is_noise(self, text: str, error: BaseException | None) -> bool:
        text = text + " " + (str(error) if error is not None else "")
        if any(path in text for path in self.paths):
            return True
        if isinstance(error, RuntimeError) and str(error) in _LOOP_GONE:
            return True
        return "never retrieved" in text and error is not None and _os_error(error) is not None

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        error = record.exc_info[1] if record.exc_info else None
        return not self.is_noise(record.getMessage(), error)

    def excepthook(self, kind, value, traceback) -> None:
        if isinstance(value, RuntimeError) and str(value) in _LOOP_GONE:
            return
        (self.previous_excepthook or sys.__excepthook__)(kind, value, traceback)

    def unraisable(self, unraisable) -> None:
        code = getattr(unraisable.object, "cr_code", None)
        if (code is not None and f"{os.sep}orbax{os.sep}" in code.co_filename) or self.is_noise(
                unraisable.err_msg or "", unraisable.exc_value):
            return
        (self.previous_hook or sys.__unraisablehook__)(unraisable)


_LOOP_GONE = ("Event loop is closed", "cannot schedule new futures after shutdown")
_AFTERMATH = _Aftermath()
