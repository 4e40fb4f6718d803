"""The live view of a training run (``train.viewer=true``): the web viewer fed by the training loop.

The training loop calls :meth:`LiveView.after_step` after every step. It renders (on the training
thread, so nothing runs beside a step) only while a browser is connected and only while the time
spent on the view stays within ``train.viewer_budget`` of the wall time since the view started:
with the default 0.1, training runs at least about 90 % of its speed without the view (one frame
of overshoot at most). Each frame shows the model as it is at that step (anchors compacted
then, :func:`cusgs_jax.view.render.from_session`). Time spent here is not charged to the run's
training clock.
"""

from __future__ import annotations

import contextlib
import logging
import time

__all__ = ["LiveView", "live_view"]

log = logging.getLogger("cusgs_jax")


class LiveView:
    """Renders a :class:`~cusgs_jax.view.server.Viewer` from a training session within a time budget.

    Attributes:
      viewer: the viewer; budget: the share of wall time it may use;
      spent_s: seconds spent rendering so far; frames: render rounds done.
    """

    def __init__(self, viewer, budget: float, clock=time.perf_counter):
        self.viewer, self.budget, self._clock = viewer, float(budget), clock
        self.started = clock()
        self.spent_s, self.frames = 0.0, 0
        self._cameras = None

    def due(self) -> bool:
        """Whether a frame may be rendered now: a browser is there and the budget allows it."""
        if not self.viewer.server.get_clients():
            return False
        return self.spent_s <= self.budget * (self._clock() - self.started)

    def after_step(self, session) -> None:
        """Show the session's model as it is now, if :meth:`due`."""
        if not self.due():
            return
        from cusgs_jax.view.render import from_session

        start = self._clock()
        model = from_session(session, cameras=self._cameras)
        self._cameras = model.cameras
        self.viewer.set_model(model)
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
def live_view(session):
    """``with live_view(session) as live:`` a :class:`LiveView` when ``train.viewer`` is on, else None;
    the server is stopped on the way out."""
    opts = session.cfg.train
    if not opts.viewer:
        yield None
        return
    from cusgs_jax.view.render import from_session
    from cusgs_jax.view.server import Viewer

    viewer = Viewer(from_session(session), port=opts.viewer_port)
    log.info("live viewer at %s (at most %.0f%% of the training time goes to it)", viewer.url,
             100 * opts.viewer_budget)
    live = LiveView(viewer, opts.viewer_budget)
    try:
        yield live
    finally:
        log.info("live viewer: %d frames, %.1f%% of the wall time", live.frames, 100 * live.share)
        live.close()
