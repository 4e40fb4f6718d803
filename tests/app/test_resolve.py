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


def test_the_voxel_size_comes_from_the_points_spacing_or_for_random_points_from_the_cameras():
    """``model.voxel_size=auto``: the SfM points' median spacing (model.anchors.auto_voxel_size); for random points the
    cameras' pixel footprint (data.random_points.random_voxel_size), finer than the random points' spacing; a set
    size is kept as it is."""
    import numpy as np
    import pytest

    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.config import Config
    from cusgs_jax.data.random_points import random_points, random_voxel_size
    from cusgs_jax.model.anchors import auto_voxel_size

    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)  # a ring of cameras at radius 4 looking at the origin
    views = np.stack([np.linalg.inv(np.array([[np.cos(a), 0, -np.sin(a), 4 * np.sin(a)], [0, -1, 0, 0],
                                              [-np.sin(a), 0, -np.cos(a), 4 * np.cos(a)], [0, 0, 0, 1]]))
                      for a in angles])
    width = height = 40
    Ks = np.tile(np.array([[40.0, 0, 20], [0, 40.0, 20], [0, 0, 1]]), (12, 1, 1))
    points, _ = random_points(views, Ks, width, height, num=5000)
    auto = Config()  # model.voxel_size=None: auto
    assert resolve_voxel_size(auto, points).model.voxel_size == pytest.approx(auto_voxel_size(points))
    rule = resolve_voxel_size(auto, points, (views, Ks, width, height)).model.voxel_size
    assert rule == pytest.approx(random_voxel_size(views, Ks, width, height)) and rule < 0.5 * auto_voxel_size(points)
    explicit = auto.replace(model=dict(voxel_size=0.05))
    assert resolve_voxel_size(explicit, points) is explicit
