"""Training wall-clock time, excluding evaluation and checkpointing."""

from __future__ import annotations

import contextlib
import time


class Clock:
    """``with clock:`` charges the block's time to ``clock.total``; ``clock.paused()`` inside it does not."""

    def __init__(self, offset: float = 0.0):
        self.total = offset
        self._start = None

    def __enter__(self):
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.total += time.perf_counter() - self._start
        self._start = None

    @contextlib.contextmanager
    def paused(self):
        """Inside a ``with clock:`` block: the time spent here is not charged (outside one nothing is)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            if self._start is not None:
                self._start += time.perf_counter() - start
