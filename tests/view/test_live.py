"""The live view's time budget (a fake viewer and clock) and a train.viewer=true run that stops its server."""

from __future__ import annotations

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
        pass

    def render_pending(self):
        self.clock.t += self.frame_s
        self.rendered += 1

    def stop(self):
        self.stopped = True


def test_rendering_stays_within_the_budget(monkeypatch):
    monkeypatch.setattr("cusgs_jax.view.render.from_session", lambda session, cameras=None: type("M", (), {"cameras": []}))
    clock = _Clock()
    viewer = _FakeViewer(clock, frame_s=0.05)
    live = LiveView(viewer, budget=0.1, clock=clock)
    for _ in range(1000):  # 1000 training steps of 10 ms
        clock.t += 0.01
        live.after_step(session=None)
    assert live.share <= 0.1 + 0.05 / clock.t  # one frame of overshoot at most
    assert live.share > 0.08 and viewer.rendered == live.frames > 10
    live.close()
    assert viewer.stopped


def test_nothing_is_rendered_without_a_browser(monkeypatch):
    clock = _Clock()
    viewer = _FakeViewer(clock, frame_s=0.05, clients=0)
    live = LiveView(viewer, budget=1.0, clock=clock)
    clock.t += 1.0
    live.after_step(session=None)
    assert viewer.rendered == 0 and live.spent_s == 0


def test_a_training_run_with_the_live_viewer_stops_its_server(tmp_path, caplog):
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    from cusgs_jax.app.run import run
    from cusgs_jax.config import compose_config
    from cusgs_jax.data.demo import generate_demo_scene
    from cusgs_jax.errors import ConfigError

    with pytest.raises(ConfigError, match="train.viewer_budget"):
        compose_config(["train.viewer_budget=0"])
    scene = generate_demo_scene(tmp_path / "scene", num_views=4, width=24, height=18, num_points=300)
    cfg = compose_config([f"data.path={scene}", "train.iterations=3", "train.progress=false", "eval.every=0",
                          "eval.save_renders=false", "train.checkpoint_every=0", "model.n_offsets=2",
                          "model.latent_dim=4", "model.hidden=8", "model.appearance_dim=4", "features=none",
                          "train.viewer=true", "train.viewer_port=0"])
    with caplog.at_level("INFO", logger="cusgs_jax"):
        run(cfg, tmp_path / "run")
    assert "live viewer at http://" in caplog.text and "live viewer: 0 frames" in caplog.text
