"""The loop (app/loop.py): the state a run starts with, fitted capacities, refusals at the start, logged rows."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.app.loop import Loop, start
from cusgs_jax.app.session import setup
from cusgs_jax.testing.runs import tiny_config as _cfg
from cusgs_jax.types import Camera


def test_start_makes_a_fresh_loop_at_step_zero_with_its_renders(tiny_scene, tmp_path):
    session = setup(_cfg(tiny_scene), tmp_path / "run")
    loop = start(session)
    assert isinstance(loop, Loop) and int(loop.state.step) == 0 and loop.curve == []
    assert loop.render is not None and loop.feature_render is None  # no feature models in TINY
    assert set(loop.tallies) == {s.name for s in session.strategies}
    session.ckpt.close()


def test_the_first_capacities_are_fitted_to_what_the_views_need(tiny_scene, tmp_path, caplog):
    """The shell probes training views and sizes the capacities by their need, whatever the config guessed."""
    from cusgs_jax.training.capacity import Capacities
    from cusgs_jax.training.render import view_work

    cfg = _cfg(tiny_scene, "model.visible_fraction=0.05", "splat.active_fraction=0.05",
               "splat.max_pairs_per_gaussian=0.05")
    with caplog.at_level("INFO", logger="cusgs_jax"):
        session = setup(cfg, tmp_path / "fitted")
        loop = start(session)
    assert "work capacities from" in caplog.text
    caps, state = loop.capacities, loop.state
    assert caps != Capacities.from_config(session.cfg)
    n = session.cfg.model.n_offsets
    assert len(session.train_idx) <= 8  # so every training view was probed
    for position, view in enumerate(session.train_idx):
        work = jax.device_get(view_work(state.anchors, state.nets, Camera.of_scene(session.scene, int(view)),
                                        jnp.int32(position), session.cfg))
        assert caps.visible_slots(state.anchors.capacity) >= work["visible_anchors"]
        assert caps.active_gaussians(state.anchors.capacity, n) >= work["active_gaussians"]
        assert caps.pairs(state.anchors.capacity, n) >= work["pairs"]


def test_a_strategy_growing_the_anchor_capacity_regrows_the_work_capacities_and_rebuilds_the_step(tiny_scene, tmp_path):
    """After a growth the step runs at Capacities.regrown (the visible fraction kept, no more active Gaussians than
    before) — the capacities the foresight prepared the step for — and the step's program is the new one."""
    import dataclasses

    from cusgs_jax.app.loop import run_strategies
    from cusgs_jax.densify import ops
    from cusgs_jax.densify.base import Tally, UpdateInfo

    class Grow:
        name = "grow"

        def due(self, step):
            return True

        def before_first_update(self, probe):
            return {}

        def update(self, state, tx, step):
            return ops.grow_capacity(state, tx, 2 * state.anchors.capacity), UpdateInfo(capacity_changed=True)

    session = setup(_cfg(tiny_scene), tmp_path / "run")
    loop = start(session)
    session = dataclasses.replace(session, strategies=(Grow(),))
    loop.tallies = {"grow": Tally()}
    before, capacity, n = loop.capacities, loop.state.anchors.capacity, session.cfg.model.n_offsets
    run_strategies(session, loop, 1)
    assert loop.state.anchors.capacity == 2 * capacity and loop.recompilations == 1
    assert loop.capacities == before.regrown(capacity, 2 * capacity, n)
    assert loop.capacities.visible_fraction == before.visible_fraction
    assert before.active_gaussians(capacity, n) <= loop.capacities.active_gaussians(2 * capacity, n) < \
        before.active_gaussians(2 * capacity, n)
    session.ckpt.close()


def test_a_scene_whose_points_no_training_view_sees_is_refused_at_the_start(tmp_path):
    """Points behind every camera would train the background alone to a black image (exit 0); refused instead."""
    from cusgs_jax.data.errors import SceneError
    from cusgs_jax.testing.scenes import object_scene

    scene = object_scene(tmp_path / "away", views=6, width=32, height=24, num_points=300, facing_away=True)
    with pytest.raises(SceneError, match=r"data\.path=.*away.*none of the \d+ initial anchors .* is seen by any of "
                                         r"the 5 training views probed.*same reconstruction"):
        start(setup(_cfg(scene, "model.voxel_size=auto"), tmp_path / "run"))
    assert not (tmp_path / "run" / "metrics.jsonl").exists()
    # the same cameras turned towards the points set up as usual
    facing = object_scene(tmp_path / "facing", views=6, width=32, height=24, num_points=300)
    assert start(setup(_cfg(facing, "model.voxel_size=auto"), tmp_path / "run2")).capacities is not None


def test_every_loss_term_far_outside_its_normal_range_is_warned_about_at_any_logged_step(caplog):
    from types import SimpleNamespace

    from cusgs_jax.app.loop import _log_row
    from cusgs_jax.config import Config

    cfg = Config()
    state = SimpleNamespace(anchors=SimpleNamespace(alive=np.ones(5, bool)), skipped=0)
    session = SimpleNamespace(cfg=cfg, banks=None, budget=SimpleNamespace(clock=SimpleNamespace(total=1.0)),
                              strategies=())
    loop = SimpleNamespace(state=state, tallies={}, replays=0, recompilations=0, alarmed=set())
    normal = dict(loss=0.5, loss_image=0.3, loss_l1=0.2, loss_feature=0.4, loss_feat_semantic_l2=0.05,
                  loss_feat_semantic_cos=0.35, psnr=9.8, visible_anchors=5, active_gaussians=20, pairs=80,
                  dropped_anchors=0, dropped_gaussians=0, dropped_pairs=0)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        row = _log_row(session, loop, cfg.train.log_every, normal, 0.1)
        assert caplog.text == ""
        # a later logged step: the image loss alone is far too large
        _log_row(session, loop, 7 * cfg.train.log_every, dict(normal, loss=720.0, loss_image=720.0), 0.1)
        _log_row(session, loop, 8 * cfg.train.log_every, dict(normal, loss=720.0, loss_image=720.0), 0.1)  # said once
        # the image loss is normal, a feature model's L2 term explodes (a stray target value of 1e6)
        _log_row(session, loop, 9 * cfg.train.log_every, dict(normal, loss=3e8, loss_feature=3e8,
                                                         loss_feat_semantic_l2=3e8), 0.1)
        _log_row(session, loop, 10 * cfg.train.log_every, dict(normal, loss=float("nan"), loss_l1=float("nan")), 0.1)
    assert row["dropped_anchors"] == row["dropped_pairs"] == 0
    assert caplog.text.count("far above the normal range") == 2 and "model.voxel_size" in caplog.text
    assert f"step {7 * cfg.train.log_every}: image loss 720" in caplog.text
    assert f"step {9 * cfg.train.log_every}: the L2 feature loss of model semantic is 3e+08" in caplog.text
    assert "features/semantic/" in caplog.text
    assert f"step {10 * cfg.train.log_every}: the loss term l1 is nan" in caplog.text


def test_an_accelerators_start_fits_the_growth_the_strategies_forecast(tiny_scene, tmp_path):
    """On an accelerator the start's capacities hold the views' need times A/alive where a strategy will grow the
    anchors into the capacity; on a CPU, or where nothing grows, what the views need now."""
    from cusgs_jax.app.loop import growth_forecast
    from cusgs_jax.training.state import init_train_state

    session = setup(_cfg(tiny_scene), tmp_path / "run")
    state, _ = init_train_state(session.cfg, session.scene.points, len(session.train_idx), session.scene.extent,
                                session.strategies, None)
    alive, capacity = int(np.sum(np.asarray(state.anchors.alive))), state.anchors.capacity
    assert growth_forecast(session, state, backend="cpu") == 1.0
    assert capacity > alive and growth_forecast(session, state, backend="gpu") == capacity / alive
    still = setup(_cfg(tiny_scene, "grow.start=100", "grow.stop=100"), tmp_path / "still")
    assert growth_forecast(still, state, backend="gpu") == 1.0  # Scaffold-GS never grows within 30 steps
    session.ckpt.close()
    still.ckpt.close()
