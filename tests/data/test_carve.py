"""data/carve.py: random starting points carved by the training views' frusta and a vote of their alpha coverage;
blank views named and ignored."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data import carve as carve_module
from cusgs_jax.data.carve import Carving, blank_views, carve, coverage_at, dilate
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


def sphere_points(radius: float, rng) -> tuple[np.ndarray, int]:
    """(points, object count): 3000 points inside the sphere and 500 on its surface, then 3000 off the hull
    (from 1.25 r to 1.25 r + 1)."""
    inside = uniform_ball(3000, radius, rng)
    surface = rng.normal(size=(500, 3))
    surface *= radius / np.linalg.norm(surface, axis=1, keepdims=True)
    far = rng.normal(size=(3000, 3))
    far *= (1.25 * radius + rng.random((3000, 1))) / np.linalg.norm(far, axis=1, keepdims=True)
    return np.concatenate([inside, surface, far]), 3500


def project(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inside [P] bool, row [P], col [P]) of ``points`` in a SIZE × SIZE view."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    v = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < SIZE) & (v >= 0) & (v < SIZE)
    return inside, np.clip(np.floor(v), 0, SIZE - 1).astype(int), np.clip(np.floor(u), 0, SIZE - 1).astype(int)


def test_a_blank_view_is_named_ignored_and_does_not_carve_the_object(caplog):
    """One training view whose alpha is 0 everywhere (the issue's 5-of-100 000 case): the object is kept, empty
    space carved as without it, the view named in the warning and in ``ignored_views``."""
    rng = np.random.default_rng(3)
    radius = 0.6
    viewmats = ring_cameras(count=25)
    Ks = intrinsics(len(viewmats))
    coverage = [sphere_silhouette(m, K, radius) for m, K in zip(viewmats, Ks)]
    coverage[7] = np.zeros((SIZE, SIZE), bool)  # blank: sees the whole sphere, shows none of it
    names = [f"train/r_{i:03d}.png" for i in range(len(viewmats))]
    points, on_object = sphere_points(radius, rng)
    assert project(points[:on_object], viewmats[7], Ks[7])[0].all()  # the blank view sees the whole object
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        keep, carving = carve(points, viewmats, Ks, SIZE, SIZE, coverage, names=names)
    assert keep[:on_object].all()  # every point of the object, its surface included
    assert not keep[on_object:].any()  # and still nothing off the hull
    assert carving.ignored_views == ("train/r_007.png",) and carving.views_with_alpha == 24
    assert carving.as_dict()["ignored_views"] == ["train/r_007.png"]
    assert "train/r_007.png" in caplog.text and "blank" in caplog.text and "1 of 25" in caplog.text
    others = [i for i in range(25) if i != 7]
    without, _ = carve(points, viewmats[others], Ks[others], SIZE, SIZE, [coverage[i] for i in others])
    np.testing.assert_array_equal(keep, without)  # the same points as if the view were not there
    # the vote alone (blank views not detected) keeps the object too: one view's transparent vote is not enough
    keep_vote, carving_vote = _carve_without_blank_detection(points, viewmats, Ks, coverage)
    assert keep_vote[:on_object].all() and carving_vote.ignored_views == () and carving_vote.views_with_alpha == 25
    assert keep_vote[on_object:].mean() < 0.01


def _carve_without_blank_detection(points, viewmats, Ks, coverage):
    saved = carve_module.EMPTY_FRACTION, carve_module.MEDIAN_FRACTION
    carve_module.EMPTY_FRACTION = carve_module.MEDIAN_FRACTION = 0.0
    try:
        return carve(points, viewmats, Ks, SIZE, SIZE, coverage)
    finally:
        carve_module.EMPTY_FRACTION, carve_module.MEDIAN_FRACTION = saved


def test_a_view_with_a_shifted_silhouette_is_outvoted():
    """A view whose silhouette is off by 10 pixels (a bad pose) is not blank and votes; it shows part of the
    object transparent, but one vote among the ~24 views that see a point does not carve it; nor do three
    among 100."""
    rng = np.random.default_rng(4)
    radius = 0.6
    viewmats = ring_cameras()
    Ks = intrinsics(len(viewmats))
    coverage = [sphere_silhouette(m, K, radius) for m, K in zip(viewmats, Ks)]
    coverage[5] = np.roll(coverage[5], 10, axis=1)
    points, on_object = sphere_points(radius, rng)
    inside, row, col = project(points[:on_object], viewmats[5], Ks[5])
    wrong = inside & ~dilate(coverage[5], 1)[row, col]
    assert wrong.mean() > 0.2  # "any view" would carve these points of the object
    keep, carving = carve(points, viewmats, Ks, SIZE, SIZE, coverage)
    assert keep[:on_object].all() and not keep[on_object:].any()
    assert carving.ignored_views == () and carving.views_with_alpha == 24
    # with many views a few broken ones are outvoted too: 3 of 100 (carving needs a twentieth, 5 of 100)
    viewmats = ring_cameras(count=100)
    Ks = intrinsics(100)
    coverage = [sphere_silhouette(m, K, radius) for m, K in zip(viewmats, Ks)]
    for i, shift in ((5, 10), (40, -10), (77, 12)):
        coverage[i] = np.roll(coverage[i], shift, axis=i % 2)
    keep, carving = carve(points, viewmats, Ks, SIZE, SIZE, coverage)
    assert keep[:on_object].all() and not keep[on_object:].any() and carving.ignored_views == ()


def test_the_vote_needs_two_views_and_a_twentieth_of_those_that_see_the_point():
    """A point seen by V views with alpha, in front of a transparent pixel in T of them: carved from
    T = max(2, V / 20) — 2 of 8, 3 of 60; seen by one view with alpha only: carved by that view."""
    point = np.zeros((1, 3))
    for count, needed in ((8, 2), (60, 3)):
        viewmats = ring_cameras(count=count, radius=40.0)  # far away: the origin is seen by all
        Ks = intrinsics(count)
        for transparent in range(needed + 3):
            coverage = [_band() if i >= transparent else _corner() for i in range(count)]
            keep, carving = carve(point, viewmats, Ks, SIZE, SIZE, coverage)
            assert carving.ignored_views == () and keep[0] == (transparent < needed), (count, transparent)
    keep, _ = carve(point, viewmats[:1], Ks[:1], SIZE, SIZE, [_corner()])
    assert not keep[0]  # the only view with alpha that sees it decides
    keep, _ = carve(point, viewmats[:2], Ks[:2], SIZE, SIZE, [_corner(), _band()])
    assert keep[0]  # one of two: kept


def _band() -> np.ndarray:
    """Coverage of the middle half of the columns: the image centre is covered."""
    covered = np.zeros((SIZE, SIZE), bool)
    covered[:, SIZE // 4:3 * SIZE // 4] = True
    return covered


def _corner() -> np.ndarray:
    """A coverage that is not blank (a 20 × 20 corner, ~10 %, a fifth of the band's) and leaves the centre
    transparent."""
    covered = np.zeros((SIZE, SIZE), bool)
    covered[:20, :20] = True
    return covered


def test_blank_views_are_empty_or_far_below_the_median():
    full = np.ones((100, 100), bool)
    some = np.zeros((100, 100), bool)
    some[:30] = True  # 30 %
    speck = np.zeros((100, 100), bool)
    speck[0, :50] = True  # 0.5 %: over 0.1 % but under a twentieth of the median (15 %)
    tiny = np.zeros((100, 100), bool)
    tiny[0, :5] = True  # 0.05 %
    assert blank_views([some, some, None, np.zeros((100, 100), bool), speck, tiny, full]) == [3, 4, 5]
    assert blank_views([speck, speck, speck]) == []  # small but like the others: an object seen small
    assert blank_views([tiny, tiny]) == [0, 1] and blank_views([None, None]) == [] and blank_views([]) == []


def test_a_record_without_ignored_views_reads_as_before():
    old = {"points": 10, "kept": 4, "outside_frusta": 2, "transparent": 4, "views_with_alpha": 3}
    record = Carving(**old)
    assert record.ignored_views == () and record.as_dict() == {**old, "ignored_views": []}


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
