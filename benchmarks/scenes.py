"""Synthetic benchmark scenes with realistic screen-space footprints."""

from __future__ import annotations

import numpy as np


def random_scene(num_gaussians: int, width: int, height: int, channels: int = 3, seed: int = 0):
    """A camera looking down +z at G Gaussians filling its frustum.

    Footprints are a few to tens of pixels wide at any resolution: the world
    scale is drawn so that ``3·f·s/z`` is log-uniform in [1.5, 15] pixels
    (3-sigma radius), i.e. 3 to 30 pixels across.

    Returns:
      dict of float32 arrays: means [G,3], quats [G,4], scales [G,3],
      opacities [G], colors [G,C], viewmat [4,4], K [3,3]; and width, height.
    """
    rng = np.random.default_rng(seed)
    focal = float(width)
    depth = rng.uniform(2.0, 8.0, num_gaussians)
    u = rng.uniform(0, width, num_gaussians)
    v = rng.uniform(0, height, num_gaussians)
    x = (u - width / 2) * depth / focal
    y = (v - height / 2) * depth / focal
    radius_px = np.exp(rng.uniform(np.log(1.5), np.log(15.0), num_gaussians))
    base = radius_px * depth / (3.0 * focal)
    scales = base[:, None] * np.exp(rng.uniform(-0.5, 0.5, (num_gaussians, 3)))
    quats = rng.normal(size=(num_gaussians, 4))
    opacities = 1.0 / (1.0 + np.exp(-rng.normal(0.0, 2.0, num_gaussians)))
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    return dict(
        means=np.stack([x, y, depth], -1).astype(np.float32),
        quats=quats.astype(np.float32),
        scales=scales.astype(np.float32),
        opacities=opacities.astype(np.float32),
        colors=rng.uniform(0, 1, (num_gaussians, channels)).astype(np.float32),
        viewmat=np.eye(4, dtype=np.float32),
        K=K.astype(np.float32),
        width=width,
        height=height,
    )
