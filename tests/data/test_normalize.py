"""The normalised world frame (data/normalize.py): invariance to similarity transforms of a COLMAP model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.normalize import WorldTransform, camera_extent, normalize_scene, principal_axes
from cusgs_jax.testing.scenes import random_rotation, transformed_scene


def _project(scene, view):
    """[P, 2] pixel positions and [P] depths of the scene's points in one view (float64)."""
    viewmat, K = scene.viewmats[view].astype(np.float64), scene.Ks[view].astype(np.float64)
    cam = scene.points.astype(np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    return uv, cam[:, 2]


def test_normalised_frame_has_extent_one_and_keeps_every_pixel(demo):
    scene = load_scene(demo, DataConfig(format="colmap", holdout_every=0))
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
    base, _ = normalize_scene(load_scene(demo, DataConfig(format="colmap", holdout_every=0)))
    moved_path = transformed_scene(demo, tmp_path / "moved", scale=scale, translation=(5.0, -3.0, 2.0))
    moved, world = normalize_scene(load_scene(moved_path, DataConfig(format="colmap", holdout_every=0)))
    extent = load_scene(demo, DataConfig(format="colmap", holdout_every=0)).extent
    assert world.scale == pytest.approx(1.0 / (scale * extent), rel=1e-4)
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
    assert dataclasses.asdict(world)["center"] == (1.0, -2.0, 3.0) and np.array_equal(world.matrix, np.eye(3))
    # records written before the rotation existed read back as the identity
    assert WorldTransform.from_dict({"scale": 0.25, "center": [1.0, -2.0, 3.0]}) == world
    assert WorldTransform.from_dict(world.as_dict()) == world


def test_rotated_world_transform_round_trip_keeps_camera_space():
    """p' = s·Q(p − c): points round-trip and camera-space coordinates only scale by s."""
    world = WorldTransform(scale=0.25, center=(1.0, -2.0, 3.0), rotation=tuple(map(tuple, random_rotation(4))))
    points = np.random.default_rng(1).normal(size=(10, 3))
    np.testing.assert_allclose(world.to_colmap(world.to_normalized(points)), points, atol=1e-12)
    viewmat = np.eye(4)
    viewmat[:3, :3] = random_rotation(5)
    viewmat[:3, 3] = [0.5, 0.1, 4.0]
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    moved = world.viewmats(viewmat[None])[0]
    cam_n = world.to_normalized(points) @ moved[:3, :3].T + moved[:3, 3]
    np.testing.assert_allclose(cam_n, world.scale * cam, atol=1e-12)
    np.testing.assert_allclose(moved[:3, :3] @ moved[:3, :3].T, np.eye(3), atol=1e-12)
    assert WorldTransform.from_dict(world.as_dict()) == world


def test_principal_axes_are_a_right_handed_equivariant_frame():
    points = np.random.default_rng(2).normal(size=(500, 3)) * [5.0, 2.0, 0.5] + [0.3, 0.0, 0.1]
    axes = principal_axes(points)
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    spread = np.var(points @ axes.T, axis=0)
    assert spread[0] > spread[1] > spread[2]
    m = random_rotation(7)
    np.testing.assert_allclose(principal_axes(points @ m.T), axes @ m.T, atol=1e-9)


@pytest.mark.parametrize("rotation_xyzw", [(0.3, -0.5, 0.2, 0.8), (0.0, 0.0, 1.0, 0.0)])
def test_principal_alignment_makes_a_rotated_model_normalise_to_the_same_frame(demo, tmp_path, rotation_xyzw):
    """data.align=principal: a rotated, scaled and moved copy of a model gives the same normalised points and
    poses as the original (so the voxel grid no longer depends on the SfM run's axes); with
    data.align=none the points differ by the rotation."""
    base, base_world = normalize_scene(load_scene(demo, DataConfig(format="colmap", holdout_every=0)),
                                       align="principal")
    moved_path = transformed_scene(demo, tmp_path / "rotated", scale=3.0, translation=(1.0, 2.0, -4.0),
                                   rotation_xyzw=rotation_xyzw)
    moved_scene = load_scene(moved_path, DataConfig(format="colmap", holdout_every=0))
    moved, world = normalize_scene(moved_scene, align="principal")
    np.testing.assert_allclose(moved.points, base.points, atol=1e-5)
    np.testing.assert_allclose(moved.viewmats, base.viewmats, atol=1e-5)
    np.testing.assert_allclose(world.to_colmap(moved.points), moved_scene.points, atol=1e-4 * moved_scene.extent)
    for view in (0, 3):  # every pixel unchanged by the frame
        uv, depth = _project(moved_scene, view)
        uv_n, depth_n = _project(moved, view)
        np.testing.assert_allclose(uv_n, uv, rtol=1e-4, atol=2e-3)
        np.testing.assert_allclose(depth_n, depth * world.scale, rtol=1e-4)
    unaligned, _ = normalize_scene(moved_scene, align="none")
    assert np.max(np.abs(unaligned.points - base.points)) > 0.1
    with pytest.raises(ValueError, match="align"):
        normalize_scene(moved_scene, align="pca")
