"""Small random inputs for the tests: Gaussian scenes (float64 NumPy) for the splatting tests,
SfM-like point clouds and PSC banks for the training tests."""

from __future__ import annotations

import numpy as np

__all__ = ["KEYS", "as_dtype", "feature_maps", "make_scene", "random_banks", "sfm_points"]

KEYS = ("means", "quats", "scales", "opacities", "colors")
"""The Gaussian parameter keys of a scene, in rasteriser argument order."""


def make_scene(seed=0, num=120, width=40, height=28, channels=3, *, behind=0, offscreen=0,
               opaque=0, focal=None, depth_range=(1.0, 6.0)):
    """Random Gaussians in a camera frustum, as float64 NumPy arrays.

    Args:
      behind: how many Gaussians to put behind the camera / in front of `near`.
      offscreen: how many to put far outside the frustum.
      opaque: how many get opacity 1 (alpha clamped at 0.999).
    Returns:
      dict with means [G,3], quats [G,4], scales [G,3], opacities [G],
      colors [G,C], viewmat [4,4], K [3,3], background [C], width, height.
    """
    rng = np.random.default_rng(seed)
    focal = focal or 0.9 * width
    z = rng.uniform(*depth_range, num)
    x = rng.uniform(-0.6, 0.6, num) * z * width / focal
    y = rng.uniform(-0.6, 0.6, num) * z * height / focal
    means = np.stack([x, y, z], -1)
    if behind:
        means[:behind, 2] = rng.uniform(-2.0, 0.009, behind)
    if offscreen:
        means[behind:behind + offscreen, 0] = rng.choice([-1, 1], offscreen) * rng.uniform(20, 40, offscreen)
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.25), (num, 3)))
    opacities = rng.uniform(0.05, 0.95, num)
    opacities[num - opaque:] = 1.0
    # A rotated, translated camera: world = camera frame rotated about y by 10°.
    angle = np.deg2rad(10.0)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    center = np.array([0.3, -0.2, -0.5])
    means = means @ rot.T + center  # camera→world
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot.T
    viewmat[:3, 3] = -rot.T @ center
    K = np.array([[focal, 0, width / 2], [0, focal * 1.05, height / 2], [0, 0, 1]])
    return dict(
        means=means, quats=rng.normal(size=(num, 4)), scales=scales, opacities=opacities,
        colors=rng.uniform(0, 1, (num, channels)), viewmat=viewmat, K=K,
        background=rng.uniform(0, 1, channels), width=width, height=height,
    )


def as_dtype(scene, dtype):
    """Scene arrays cast to `dtype` (ints untouched)."""
    return {k: (np.asarray(v, dtype) if isinstance(v, np.ndarray) else v) for k, v in scene.items()}


def sfm_points(num: int = 400, seed: int = 0) -> np.ndarray:
    """[P, 3] float64 points uniform in the box [-1, 1]² × [2, 4] (in front of an identity camera)."""
    points = np.random.default_rng(seed).uniform(-1, 1, (num, 3))
    points[:, 2] += 3.0
    return points


def random_banks(shapes: dict[str, tuple[int, int]], seed: int = 1) -> dict[str, np.ndarray]:
    """{model: [M, D] float32 standard-normal PSC entries}, drawn in the order of ``shapes``."""
    rng = np.random.default_rng(seed)
    return {name: rng.normal(size=shape).astype(np.float32) for name, shape in shapes.items()}


def feature_maps(n: int = 3, h: int = 5, w: int = 7, d: int = 4, seed: int = 0) -> np.ndarray:
    """[n, h, w, d] float32 standard-normal feature maps with a zero ("no target") pixel in
    view 0 and, when n > 1 and h > 2, a zero row in view 1."""
    maps = np.random.default_rng(seed).normal(size=(n, h, w, d)).astype(np.float32)
    maps[0, 0, 0] = 0.0
    if n > 1 and h > 2:
        maps[1, 2, :] = 0.0
    return maps
