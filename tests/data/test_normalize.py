"""The normalised world frame (data/normalize.py): invariance to similarity transforms of a COLMAP model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cusgs_jax.data.colmap import load_scene
from cusgs_jax.data.normalize import WorldTransform, camera_extent, normalize_scene
from cusgs_jax.testing.scenes import transformed_scene


def _project(scene, view):
    """[P, 2] pixel positions and [P] depths of the scene's points in one view (float64)."""
    viewmat, K = scene.viewmats[view].astype(np.float64), scene.Ks[view].astype(np.float64)
    cam = scene.points.astype(np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    return uv, cam[:, 2]


def test_normalised_frame_has_extent_one_and_keeps_every_pixel(demo):
    scene = load_scene(demo, holdout_every=0)
    normalized, world = normalize_scene(scene)
    assert normalized.extent == 1.0
    extent, center = camera_extent(normalized.camera_centers, normalized.points)
    assert extent == pytest.approx(1.0, rel=1e-5) and np.allclose(center, 0.0, atol=1e-5)
    assert world.scale == pytest.approx(1.0 / scene.extent, rel=1e-6)
    for view in (0, 3):
        uv, depth = _project(scene, view)
        uv_n, depth_n = _project(normalized, view)
        np.testing.assert_allclose(uv_n, uv, rtol=1e-4, atol=2e-3)  # pixels unchanged (float32 poses)
        np.testing.assert_allclose(depth_n, depth * world.scale, rtol=1e-4)  # depths in extent units
    np.testing.assert_allclose(world.to_colmap(normalized.points), scene.points, atol=1e-4 * scene.extent)
    assert normalized.images is scene.images and np.array_equal(normalized.Ks, scene.Ks)


@pytest.mark.parametrize("scale", [1000.0, 0.001])
def test_similarity_transformed_model_normalises_to_the_same_frame(demo, tmp_path, scale):
    """The same capture at another scale and origin (pycolmap Sim3d): identical normalised points and poses."""
    base, _ = normalize_scene(load_scene(demo, holdout_every=0))
    moved_path = transformed_scene(demo, tmp_path / "moved", scale=scale, translation=(5.0, -3.0, 2.0))
    moved, world = normalize_scene(load_scene(moved_path, holdout_every=0))
    assert world.scale == pytest.approx(1.0 / (scale * load_scene(demo, holdout_every=0).extent), rel=1e-4)
    np.testing.assert_allclose(moved.points, base.points, atol=1e-5)
    np.testing.assert_allclose(moved.viewmats, base.viewmats, atol=1e-5)


def test_coincident_cameras_take_the_extent_from_the_points():
    centers = np.zeros((3, 3))
    points = np.random.default_rng(0).normal(size=(100, 3)) * 10
    extent, center = camera_extent(centers, points)
    assert extent == pytest.approx(1.1 * np.percentile(np.linalg.norm(points, axis=-1), 90))
    assert np.array_equal(center, np.zeros(3))


def test_world_transform_round_trip_and_viewmats():
    world = WorldTransform(scale=0.25, center=(1.0, -2.0, 3.0))
    points = np.random.default_rng(1).normal(size=(10, 3))
    np.testing.assert_allclose(world.to_colmap(world.to_normalized(points)), points, atol=1e-12)
    viewmat = np.eye(4)
    viewmat[:3, 3] = [0.5, 0.1, 4.0]
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    moved = world.viewmats(viewmat[None])[0]
    cam_n = world.to_normalized(points) @ moved[:3, :3].T + moved[:3, 3]
    np.testing.assert_allclose(cam_n, world.scale * cam, atol=1e-12)  # camera space scales by s
    assert dataclasses.asdict(world) == {"scale": 0.25, "center": (1.0, -2.0, 3.0)}
