"""The live view of a training run (``train.viewer=true``): the web viewer fed by the training loop.

The training loop hands :func:`live_view` a ``snapshot`` function: called with no argument, it
returns the :class:`~cusgs_jax.view.render.ViewModel` of the model as it is at that moment (anchors
compacted then; :func:`cusgs_jax.view.render.view_model`). The viewer reads nothing of the run but
these frozen snapshots. The loop calls :meth:`LiveView.after_step` after every step. It renders
(on the training thread, so nothing runs beside a step) only while a browser is connected and only
while the time spent on the view stays within ``train.viewer_budget`` of the wall time since the
view started: with the default 0.1, training runs at least about 90 % of its speed without the
view (one frame of overshoot at most); ``snapshot`` is called only for a frame that is rendered.
Time spent here is not charged to the run's training clock.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator

from cusgs_jax.config import TrainOptions
from cusgs_jax.view.render import ViewModel
from cusgs_jax.view.server import Viewer  # viser (the viewer extra) is imported only when a Viewer starts

__all__ = ["LiveView", "live_view"]

log = logging.getLogger("cusgs_jax")

Snapshot = Callable[[], ViewModel]
"""``snapshot() -> ViewModel``: the model as it is now."""


class LiveView:
    """Renders a :class:`~cusgs_jax.view.server.Viewer` from a training run's snapshots within a time budget.

    Attributes:
      viewer: the viewer; budget: the share of wall time it may use; snapshot: the run's
      :data:`Snapshot`; spent_s: seconds spent rendering so far; frames: render rounds done.
    """

    def __init__(self, viewer: Viewer, budget: float, snapshot: Snapshot,
                 clock: Callable[[], float] = time.perf_counter):
        self.viewer, self.budget, self.snapshot, self._clock = viewer, float(budget), snapshot, clock
        self.started = clock()
        self.spent_s, self.frames = 0.0, 0

    def due(self) -> bool:
        """Whether a frame may be rendered now: a browser is there and the budget allows it."""
        if not self.viewer.server.get_clients():
            return False
        return self.spent_s <= self.budget * (self._clock() - self.started)

    def after_step(self) -> None:
        """Show the model as it is now (a fresh :attr:`snapshot`), if :meth:`due`."""
        if not self.due():
            return
        start = self._clock()
        self.viewer.set_model(self.snapshot())
        self.viewer.render_pending()
        self.spent_s += self._clock() - start
        self.frames += 1

    def close(self) -> None:
        self.viewer.stop()

    @property
    def share(self) -> float:
        """Share of the wall time since the start spent on the view."""
        return self.spent_s / max(self._clock() - self.started, 1e-9)


@contextlib.contextmanager
def live_view(opts: TrainOptions, snapshot: Snapshot) -> Iterator[LiveView | None]:
    """``with live_view(cfg.train, snapshot) as live:`` a :class:`LiveView` of ``snapshot`` when
    ``opts.viewer`` is on (the server starts on ``snapshot()``), else None (``snapshot`` is never
    called); the server is stopped on the way out."""
    if not opts.viewer:
        yield None
        return
    viewer = Viewer(snapshot(), port=opts.viewer_port)
    log.info("live viewer at %s (at most %.0f%% of the training time goes to it)", viewer.url,
             100 * opts.viewer_budget)
    live = LiveView(viewer, opts.viewer_budget, snapshot)
    try:
        yield live
    finally:
        log.info("live viewer: %d frames, %.1f%% of the wall time", live.frames, 100 * live.share)
        live.close()
