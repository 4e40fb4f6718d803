"""app/xla_cache.py and the run's persistent compilation cache: a rerun loads its programs instead of compiling."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import pytest

from cusgs_jax.app import xla_cache
from cusgs_jax.data.demo import generate_demo_scene


def test_auto_keeps_a_folder_the_process_chose_and_otherwise_uses_the_cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "cache"))
    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", None)
        assert xla_cache.resolve_cache_dir("auto") == tmp_path / "cache" / "xla"
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "chosen"))
        assert xla_cache.resolve_cache_dir("auto") == tmp_path / "chosen"
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    assert xla_cache.resolve_cache_dir(None) is None
    assert xla_cache.resolve_cache_dir("~/x") == xla_cache.pathlib.Path.home() / "x"


RUN = ["train.iterations=6", "train.checkpoint_every=0", "train.progress=false", "eval.every=3",
       "eval.save_renders=false", "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16",
       "model.appearance_dim=8", "features=none", "prune=none", "grow.start=100"]


@pytest.mark.slow
def test_a_rerun_loads_every_program_from_the_cache_and_the_budget_covers_the_process(tmp_path):
    """Two identical runs in fresh processes sharing train.compilation_cache: the first compiles and
    stores, the second loads them all (train step once, evaluation render once in each), and each run's
    ``time`` stages add up to its total, which is within the process's own wall time."""
    scene = generate_demo_scene(tmp_path / "scene", num_views=6, width=40, height=30, num_points=600)
    cache = tmp_path / "xla"
    results = []
    for name in ("first", "second"):
        cmd = [sys.executable, "-m", "cusgs_jax.app.train", f"data.path={scene}", *RUN,
               f"train.compilation_cache={cache}", f"hydra.run.dir={tmp_path / name}"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                              env={**os.environ, "JAX_COMPILATION_CACHE_DIR": ""})
        assert done.returncode == 0, done.stderr[-3000:]
        results.append(json.loads((tmp_path / name / "eval.json").read_text()))
        assert "XLA compilations" in done.stdout + done.stderr and "time " in done.stdout + done.stderr
    first, second = (r["compilations"] for r in results)
    assert first["train_step"] == 1 == second["train_step"]
    assert first["evaluation_renders"] == 1 == second["evaluation_renders"]
    assert first["compiled"] > 0 and first["from_cache"] == 0
    assert second["compiled"] == 0 and second["from_cache"] == second["count"] == first["count"]
    assert second["backend_seconds"] < 0.5 * first["backend_seconds"]
    assert any(cache.iterdir())
    for result in results:
        time_budget = result["time"]
        parts = sum(v for k, v in time_budget.items() if k not in ("total", "compile"))  # compile overlaps the stages
        assert parts == pytest.approx(time_budget["total"], abs=0.01)
        assert time_budget["train_steps"] > 0 and time_budget["evaluation"] > 0 and time_budget["load"] > 0
    assert results[0]["psnr"] == results[1]["psnr"]  # loaded programs are the compiled ones: same numbers


def test_a_cache_dir_that_is_a_file_is_refused_naming_the_variable(tmp_path, monkeypatch):
    from cusgs_jax.data.demo.room import cached_scene
    from cusgs_jax.errors import UserError

    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("CUSGS_CACHE_DIR", str(tmp_path / "a-file"))
    with pytest.raises(UserError, match="a-file is a file, not a folder; point CUSGS_CACHE_DIR at a folder"):
        cached_scene(tmp_path / "a-file" / "demo", lambda tmp: None)
