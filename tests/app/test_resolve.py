"""app/resolve.py: a run's configuration resolved once for its scene — every auto setting, and the facts it
was resolved from."""

from __future__ import annotations

from cusgs_jax.app.resolve import resolve_for_scene
from cusgs_jax.compose import compose_config
from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.normalize import normalize_scene
from cusgs_jax.testing.transforms_scenes import write_blender_scene, write_nerfstudio_scene


def _resolved(path, *overrides):
    cfg = compose_config([f"data.path={path}", "data.random_points=2000", *overrides])
    scene, _ = normalize_scene(load_scene(path, cfg.data, seed=cfg.train.seed))
    return resolve_for_scene(cfg, scene)


def test_a_carved_blender_capture_is_resolved_white_with_early_culling_off(tmp_path):
    truth = write_blender_scene(tmp_path / "lego", train=6, test=2, width=40, height=30)
    cfg, facts = _resolved(truth["root"])
    assert facts.random_start and facts.carved_by_coverage and facts.layout == "blender" and not facts.demo
    assert cfg.splat.background == (1.0, 1.0, 1.0) and cfg.model.voxel_size > 0 and cfg.features.models == ()
    assert cfg.grow.early_cull == "off"  # carving by alpha left almost nothing for it (experiments/README.md)
    assert _resolved(truth["root"], "data.carve=none").cfg.grow.early_cull == "on"  # nothing carved: on


def test_a_random_start_without_alpha_gets_early_culling_and_scene_points_never_do(tmp_path):
    ns = write_nerfstudio_scene(tmp_path / "ns", n=9, width=40, height=30, fl=(35.0, 37.5), c=(20.0, 16.25))
    cfg, facts = _resolved(ns["root"])
    assert facts.random_start and not facts.carved_by_coverage and cfg.grow.early_cull == "on"
    assert _resolved(ns["root"], "grow.early_cull=off").cfg.grow.early_cull == "off"  # a set value is kept
    demo = generate_demo_scene(tmp_path / "demo", width=40, height=30, num_views=4, num_points=1500)
    cfg, facts = _resolved(demo, "model.voxel_size=0.02")
    assert not facts.random_start and cfg.grow.early_cull == "off" and cfg.model.voxel_size == 0.02
    assert cfg.splat.background == (0.0, 0.0, 0.0) and facts.points == len(load_scene(demo, DataConfig()).points)
