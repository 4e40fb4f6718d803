"""data/carve.py: random starting points carved by the training views' frusta and alpha coverage."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.carve import carve, coverage_at, dilate
from cusgs_jax.errors import UserError

SIZE = 64
FOCAL = 70.0


def look_at(eye: np.ndarray, target=np.zeros(3)) -> np.ndarray:
    """[4, 4] world→camera (OpenCV: x right, y down, z forward) of a camera at ``eye`` looking at ``target``."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = rotation, -rotation @ eye
    return viewmat


def ring_cameras(count: int = 24, radius: float = 4.0, seed: int = 0) -> np.ndarray:
    """[V, 4, 4] cameras spread over a sphere of ``radius`` (Fibonacci directions), all looking at the origin."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5 ** 0.5) * i
    dirs = np.stack([np.sqrt(1 - z ** 2) * np.cos(phi), np.sqrt(1 - z ** 2) * np.sin(phi), z], axis=1)
    return np.stack([look_at(radius * d) for d in dirs])


def intrinsics(count: int) -> np.ndarray:
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]], np.float64)
    return np.repeat(K[None], count, axis=0)


def sphere_silhouette(viewmat: np.ndarray, K: np.ndarray, radius: float) -> np.ndarray:
    """[H, W] bool: the pixels whose centre ray meets the sphere of ``radius`` at the origin (analytic)."""
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    eye = -rotation.T @ translation
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    rays = rays_cam @ rotation  # to world: R^T d
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    b = rays @ eye
    return b ** 2 - (eye @ eye - radius ** 2) >= 0


def uniform_ball(count: int, radius: float, rng) -> np.ndarray:
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * radius * rng.random((count, 1)) ** (1 / 3)


def test_every_point_of_the_sphere_survives_and_every_point_off_its_hull_is_dropped():
    rng = np.random.default_rng(0)
    viewmats = ring_cameras()
    Ks = intrinsics(len(viewmats))
    radius = 0.6
    coverage = [sphere_silhouette(m, K, radius) for m, K in zip(viewmats, Ks)]
    inside = uniform_ball(3000, radius, rng)
    surface = rng.normal(size=(500, 3))
    surface *= radius / np.linalg.norm(surface, axis=1, keepdims=True)  # on the surface itself
    far = rng.normal(size=(3000, 3))
    far *= (1.25 * radius + rng.random((3000, 1))) / np.linalg.norm(far, axis=1, keepdims=True)  # off the hull
    keep, carving = carve(np.concatenate([inside, surface, far]), viewmats, Ks, SIZE, SIZE, coverage)
    assert keep[:3500].all()  # nothing of the object is dropped, its surface included
    assert not keep[3500:].any()  # the 24 silhouettes' hull lies within 1.25 r of the sphere
    assert carving.points == 6500 and carving.kept == 3500 and carving.views_with_alpha == 24
    assert carving.transparent + carving.outside_frusta == 3000


def test_without_alpha_only_the_frusta_carve():
    viewmats = ring_cameras(count=6)[:1]  # one camera at radius 4 looking at the origin
    Ks = intrinsics(1)
    eye = -viewmats[0, :3, :3].T @ viewmats[0, :3, 3]
    forward = -eye / np.linalg.norm(eye)
    points = np.stack([np.zeros(3),  # in view
                       eye - forward,  # behind the camera
                       10.0 * np.cross(forward, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(forward, [0, 0, 1.0]))])
    keep, carving = carve(points, viewmats, Ks, SIZE, SIZE)
    assert keep.tolist() == [True, False, False]
    assert carving.outside_frusta == 2 and carving.transparent == 0 and carving.views_with_alpha == 0


def test_carving_does_not_depend_on_the_scene_scale_rotation_or_origin():
    rng = np.random.default_rng(1)
    viewmats = ring_cameras(count=12)
    Ks = intrinsics(len(viewmats))
    coverage = [sphere_silhouette(m, K, 0.7) for m, K in zip(viewmats, Ks)]
    points = rng.uniform(-2, 2, size=(4000, 3))
    keep, _ = carve(points, viewmats, Ks, SIZE, SIZE, coverage)
    scale, shift = 37.5, np.array([120.0, -3.0, 0.5])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    moved = scale * points @ rotation.T + shift
    moved_views = viewmats.copy()
    for m, original in zip(moved_views, viewmats):  # the same cameras in the moved frame (coordinates × scale)
        m[:3, :3] = original[:3, :3] @ rotation.T
        m[:3, 3] = scale * original[:3, 3] - m[:3, :3] @ shift
    moved_keep, _ = carve(moved, moved_views, Ks, SIZE, SIZE, coverage)
    assert 0 < keep.sum() < len(points)
    np.testing.assert_array_equal(moved_keep, keep)


def test_views_without_alpha_carve_by_frustum_only():
    viewmats = ring_cameras(count=8)
    Ks = intrinsics(len(viewmats))
    radius = 0.5
    with_alpha = [sphere_silhouette(m, K, radius) if i % 2 == 0 else None
                  for i, (m, K) in enumerate(zip(viewmats, Ks))]
    rng = np.random.default_rng(2)
    points = rng.uniform(-1.5, 1.5, size=(3000, 3))
    keep, carving = carve(points, viewmats, Ks, SIZE, SIZE, with_alpha)
    only_alpha_views, _ = carve(points, viewmats[::2], Ks[::2], SIZE, SIZE, with_alpha[::2])
    frusta_rest, _ = carve(points, viewmats[1::2], Ks[1::2], SIZE, SIZE)
    frusta_alpha, _ = carve(points, viewmats[::2], Ks[::2], SIZE, SIZE)
    # a point survives when the alpha views keep it (or none of them sees it) and some view sees it
    seen_by_alpha = frusta_alpha
    expected = (only_alpha_views | ~seen_by_alpha) & (frusta_rest | frusta_alpha)
    np.testing.assert_array_equal(keep, expected)
    assert carving.views_with_alpha == 4 and carving.transparent > 0


def test_coverage_at_a_smaller_size_keeps_any_covered_pixel_and_dilation_grows_by_a_pixel():
    alpha = np.zeros((8, 8))
    alpha[5, 2] = 0.01
    covered = coverage_at(alpha, (4, 4))
    assert covered.sum() == 1 and covered[2, 1]
    grown = dilate(covered, 1)
    assert grown.sum() == 9 and grown[1:4, 0:3].all()
    np.testing.assert_array_equal(coverage_at(alpha, (8, 8)), alpha > 0)


def test_a_bad_carve_setting_is_refused_naming_it():
    with pytest.raises(UserError, match="data.carve"):
        DataConfig(carve="always")
