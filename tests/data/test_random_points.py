"""Random initial points for layouts without points (data/random_points.py) and the auto voxel size on them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cusgs_jax.data.normalize import camera_centers
from cusgs_jax.data.random_points import (GREY, RAY_DEPTHS, random_box, random_points, random_voxel_size, ray_points,
                                         resolve_random_init)
from cusgs_jax.model.anchors import auto_voxel_size
from cusgs_jax.testing.transforms_scenes import opencv_look_at, orbit_eyes

W = H = 80
ANGLE = 0.6911  # NeRF-synthetic's camera_angle_x


def _K(views, angle=ANGLE, width=W):
    f = 0.5 * width / math.tan(0.5 * angle)
    return np.repeat(np.array([[[f, 0, width / 2], [0, f, H / 2], [0, 0, 1]]]), views, 0)


def _ring(n=20, radius=4.0311, target=(0.0, 0.0, 0.0), seed=0):
    return np.stack([opencv_look_at(eye + np.asarray(target), target)
                     for eye in orbit_eyes(n, radius, seed)])


def test_nerf_synthetic_like_cameras_give_the_3dgs_cube():
    """Cameras on a sphere of radius 4.03 with FoV 0.69 look at the origin: the cube is centred there with
    half-side r·tan(FoV/2) ≈ 1.45 (3DGS uses ±1.3)."""
    center, half = random_box(_ring(), _K(20), W, H)
    np.testing.assert_allclose(center, 0.0, atol=1e-9)
    assert half == pytest.approx(4.0311 * math.tan(0.5 * ANGLE), rel=1e-6)
    assert 1.3 < half < 1.6


def test_box_follows_the_cameras_target_and_scale():
    center, half = random_box(_ring(target=(5.0, -2.0, 1.0)), _K(20), W, H)
    np.testing.assert_allclose(center, [5.0, -2.0, 1.0], atol=1e-9)
    scaled = _ring(target=(5.0, -2.0, 1.0))
    scaled[:, :3, 3] *= 10.0  # the same capture 10x larger
    center10, half10 = random_box(scaled, _K(20), W, H)
    np.testing.assert_allclose(center10, [50.0, -20.0, 10.0], atol=1e-7)
    assert half10 == pytest.approx(10 * half)


def test_forward_facing_cameras_fall_back_in_front_of_them():
    """Parallel optical axes (a forward-facing capture) have no nearest point: the cube sits one camera
    extent ahead of the mean camera centre."""
    eyes = np.array([(x, y, 0.0) for x in (-1.0, 0.0, 1.0) for y in (-0.5, 0.5)])
    views = np.stack([opencv_look_at(eye, eye + (0.0, 0.0, 10.0), up=(0.0, -1.0, 0.0)) for eye in eyes])
    center, half = random_box(views, _K(6), W, H)
    extent = 1.1 * np.max(np.linalg.norm(eyes - eyes.mean(0), axis=-1))
    np.testing.assert_allclose(center, [0.0, 0.0, extent], atol=1e-9)
    assert half > 0


def test_single_camera():
    center, half = random_box(_ring(1), _K(1), W, H)
    assert np.all(np.isfinite(center)) and half > 0


def test_points_are_uniform_deterministic_grey():
    views, Ks = _ring(), _K(20)
    points, colors = random_points(views, Ks, W, H, num=5000, seed=3)
    center, half = random_box(views, Ks, W, H)
    assert points.shape == (5000, 3) and points.dtype == np.float64
    assert colors.shape == (5000, 3) and colors.dtype == np.uint8 and np.all(colors == GREY)
    assert np.all(np.abs(points - center) <= half)
    assert np.all(np.abs(points.mean(0) - center) < 0.05 * half)
    np.testing.assert_array_equal(points, random_points(views, Ks, W, H, num=5000, seed=3)[0])
    assert not np.array_equal(points, random_points(views, Ks, W, H, num=5000, seed=4)[0])


def _seen_by(views, Ks, points, distance):
    """[N, V] bool: point n lies in front of camera v at a depth in RAY_DEPTHS × distance and inside its image."""
    cam = np.einsum("vij,nj->nvi", views[:, :3, :3], points) + views[None, :, :3, 3]  # [N, V, 3]
    z = cam[..., 2]
    u = Ks[None, :, 0, 0] * cam[..., 0] / z + Ks[None, :, 0, 2]
    v = Ks[None, :, 1, 1] * cam[..., 1] / z + Ks[None, :, 1, 2]
    lo, hi = RAY_DEPTHS[0] * distance, RAY_DEPTHS[1] * distance
    tol = 1e-9 * distance
    return (z >= lo - tol) & (z <= hi + tol) & (u >= -1e-6) & (u <= W + 1e-6) & (v >= -1e-6) & (v <= H + 1e-6)


def test_ray_points_lie_on_training_rays_at_the_rule_depths():
    """Every ray point lies in front of some camera at a depth in [½ D, 2½ D] (D the median distance of the
    cameras to the cube's centre) and projects inside its image; the cameras are drawn evenly; depths fill the
    range (not only the cube)."""
    views, Ks = _ring(), _K(20)
    center, _ = random_box(views, Ks, W, H)
    distance = np.median(np.linalg.norm(camera_centers(views) - center, axis=-1))
    points = ray_points(views, Ks, W, H, 4000, np.random.default_rng(0))
    seen = _seen_by(views, Ks, points, distance)
    assert points.shape == (4000, 3) and np.all(seen.any(axis=1))
    depth = np.linalg.norm(points - center, axis=-1)
    assert np.mean(depth > distance) > 0.2  # far beyond the cube (half-side 0.36 D): walls are reached


def test_ray_points_follow_the_capture_scale_and_pose():
    """A similarity transform of the cameras moves the ray points with it (same seed): nothing depends on the
    capture's arbitrary scale, origin or rotation."""
    views, Ks = _ring(), _K(20)
    rotation = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    scale, shift = 7.0, np.array([3.0, -1.0, 2.0])
    moved = views.copy()  # world x' = s R x + c: view' = [R_v Rᵀ, s t_v − R_v Rᵀ c]
    moved[:, :3, :3] = views[:, :3, :3] @ rotation.T
    moved[:, :3, 3] = scale * views[:, :3, 3] - np.einsum("vij,j->vi", moved[:, :3, :3], shift)
    a = ray_points(views, Ks, W, H, 500, np.random.default_rng(2))
    b = ray_points(moved, Ks, W, H, 500, np.random.default_rng(2))
    np.testing.assert_allclose(b, scale * a @ rotation.T + shift, atol=1e-9)


def test_cube_and_rays_splits_the_points():
    views, Ks = _ring(), _K(20)
    center, half = random_box(views, Ks, W, H)
    points, colors = random_points(views, Ks, W, H, num=3001, seed=4, init="cube_and_rays")
    assert points.shape == (3001, 3) and np.all(colors == GREY)
    cube, rays = points[:1501], points[1501:]
    assert np.all(np.abs(cube - center) <= half)
    distance = np.median(np.linalg.norm(camera_centers(views) - center, axis=-1))
    assert np.all(_seen_by(views, Ks, rays, distance).any(axis=1))
    np.testing.assert_array_equal(points, random_points(views, Ks, W, H, num=3001, seed=4, init="cube_and_rays")[0])
    with pytest.raises(ValueError, match="init='sphere'"):
        random_points(views, Ks, W, H, num=10, init="sphere")


def test_auto_rule_by_layout():
    assert resolve_random_init("auto", "blender") == "cube"
    assert resolve_random_init("auto", "nerfstudio") == "cube_and_rays"
    assert resolve_random_init("cube", "nerfstudio") == "cube" and resolve_random_init("cube_and_rays", "blender") \
        == "cube_and_rays"
    with pytest.raises(ValueError, match="resolve 'auto' first"):
        random_points(_ring(), _K(20), W, H, num=10, init="auto")


def test_auto_voxel_size_is_the_uniform_spacing():
    """model.voxel_size=auto on N uniform points in a cube of side 2h is 2h·(3 ln2 / 4πN)^(1/3): a voxel
    holds ~0.165 points, so ~92 % of the points become anchors (Scaffold-GS: one anchor per point)."""
    views, Ks = _ring(), _K(20)
    num = 20_000
    points, _ = random_points(views, Ks, W, H, num=num)
    _, half = random_box(views, Ks, W, H)
    expected = 2 * half * (3 * math.log(2) / (4 * math.pi * num)) ** (1 / 3)
    voxel = auto_voxel_size(points)
    assert voxel == pytest.approx(expected, rel=0.1)
    anchors = len(np.unique(np.floor(points / voxel), axis=0))
    assert 0.8 * num < anchors < 0.97 * num


def test_random_voxel_size_is_half_a_pixel_footprint():
    """voxel_size=auto for random points: 0.5 × camera distance / focal, whatever the number of points,
    and it scales with the scene (a 10× larger copy of the cameras gives a 10× larger voxel)."""
    views, Ks = _ring(), _K(20)
    f = 0.5 * W / math.tan(0.5 * ANGLE)
    assert random_voxel_size(views, Ks, W, H) == pytest.approx(0.5 * 4.0311 / f, rel=1e-6)
    big = views.copy()
    big[:, :3, 3] *= 10.0
    assert random_voxel_size(big, Ks, W, H) == pytest.approx(10 * 0.5 * 4.0311 / f, rel=1e-6)
    twice = _K(20, width=2 * W)  # twice the pixels across the same field of view: half the footprint
    assert random_voxel_size(views, twice, 2 * W, 2 * H) == pytest.approx(0.25 * 4.0311 / f, rel=1e-6)
