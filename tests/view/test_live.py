"""The live view's time budget (a fake viewer and clock; snapshots taken only for frames rendered) and a
train.viewer=true run that hands the viewer frozen ViewModels of its model and stops its server."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.view.live import LiveView


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class _FakeViewer:
    def __init__(self, clock, frame_s, clients=1):
        self.clock, self.frame_s, self.rendered, self.stopped = clock, frame_s, 0, False
        self.server = self
        self.clients = {i: object() for i in range(clients)}

    def get_clients(self):
        return self.clients

    def set_model(self, model):
        self.model = model

    def render_pending(self):
        self.clock.t += self.frame_s
        self.rendered += 1

    def stop(self):
        self.stopped = True


class _Snapshots:
    """A snapshot function counting its calls; each call returns a new stand-in model."""

    def __init__(self):
        self.calls = 0

    def __call__(self):
        self.calls += 1
        return ("model", self.calls)


def test_rendering_stays_within_the_budget():
    clock, snapshot = _Clock(), _Snapshots()
    viewer = _FakeViewer(clock, frame_s=0.05)
    live = LiveView(viewer, budget=0.1, snapshot=snapshot, clock=clock)
    for _ in range(1000):  # 1000 training steps of 10 ms
        clock.t += 0.01
        live.after_step()
    assert live.share <= 0.1 + 0.05 / clock.t  # one frame of overshoot at most
    assert live.share > 0.08 and viewer.rendered == live.frames > 10
    assert snapshot.calls == live.frames and viewer.model == ("model", live.frames)  # one fresh snapshot a frame
    live.close()
    assert viewer.stopped


def test_nothing_is_rendered_without_a_browser(monkeypatch):
    clock, snapshot = _Clock(), _Snapshots()
    viewer = _FakeViewer(clock, frame_s=0.05, clients=0)
    live = LiveView(viewer, budget=1.0, snapshot=snapshot, clock=clock)
    clock.t += 1.0
    live.after_step()
    assert viewer.rendered == 0 and live.spent_s == 0 and snapshot.calls == 0  # nothing compacted for nobody


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass, out of the default run (kept under 8 minutes)
def test_a_training_run_shows_view_models_of_its_steps_and_stops_its_server(tmp_path, caplog, monkeypatch):
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    from cusgs_jax.app.run import run
    from cusgs_jax.compose import compose_config
    from cusgs_jax.data.demo import generate_demo_scene
    from cusgs_jax.errors import ConfigError
    from cusgs_jax.view.render import ViewModel
    from cusgs_jax.view.server import Viewer

    shown, stopped = [], []
    monkeypatch.setattr(LiveView, "due", lambda self: True)  # as if a browser were there, with budget to spare
    monkeypatch.setattr(Viewer, "set_model", lambda self, model: shown.append(model))
    stop = Viewer.stop
    monkeypatch.setattr(Viewer, "stop", lambda self: (stopped.append(self), stop(self)))

    with pytest.raises(ConfigError, match="train.viewer_budget"):
        compose_config(["train.viewer_budget=0"])
    scene = generate_demo_scene(tmp_path / "scene", num_views=4, width=24, height=18, num_points=300)
    cfg = compose_config([f"data.path={scene}", "train.iterations=3", "train.progress=false", "eval.every=0",
                          "eval.save_renders=false", "train.checkpoint_every=0", "model.n_offsets=2",
                          "model.latent_dim=4", "model.hidden=8", "model.appearance_dim=4", "features=none",
                          "train.viewer=true", "train.viewer_port=0"])
    with caplog.at_level("INFO", logger="cusgs_jax"):
        run(cfg, tmp_path / "run")
    assert "live viewer at http://" in caplog.text and "live viewer: 3 frames" in caplog.text and len(stopped) == 1
    assert len(shown) == 3 and all(isinstance(m, ViewModel) for m in shown)  # one snapshot after each step
    first = shown[0]
    assert [c[0] for c in first.cameras] == ["train 0", "train 1", "train 2", "held-out 0"]
    assert all(m.cameras is first.cameras for m in shown)  # the camera list is built once per run
    assert (first.cameras[0][3], first.cameras[0][4]) == (24, 18) and first.banks is None
    assert first.anchors.capacity % 64 == 0 and first.nets["appearance"].shape == (1, 4)  # compacted; mean embedding
    # Each snapshot owns its arrays (the step donates the state's: shared ones would be deleted by the next
    # step) and is the model as it was at its step, not the latest one.
    first_w, last_w = (np.asarray(m.nets["decoder"]["opacity"]["w0"]) for m in (shown[0], shown[-1]))
    assert not np.array_equal(first_w, last_w)
