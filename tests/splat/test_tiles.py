"""Tile binning against a brute-force per-tile list."""

from __future__ import annotations

import numpy as np
import pytest

import jax.numpy as jnp
from cusgs_jax.splat.tiles import TileGrid, intersect_tiles, tile_bounds


def _random_footprints(seed, num, width, height):
    rng = np.random.default_rng(seed)
    means2d = rng.uniform(-20, [width + 20, height + 20], (num, 2)).astype(np.float32)
    radii = np.ceil(rng.uniform(0, 25, (num, 2))).astype(np.float32)
    depths = rng.choice(np.linspace(1, 5, 40), num).astype(np.float32)  # with ties
    visible = rng.uniform(size=num) > 0.2
    return means2d, radii, depths, visible


def _brute_force(means2d, radii, depths, visible, grid):
    order = sorted(np.nonzero(visible)[0], key=lambda g: (depths[g], g))
    box = np.asarray(tile_bounds(jnp.asarray(means2d), jnp.asarray(radii), grid))
    per_tile = [[] for _ in range(grid.num_tiles)]
    for g in order:
        x0, y0, x1, y1 = box[g]
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                per_tile[ty * grid.tiles_x + tx].append(g)
    return per_tile


def test_intersections_match_brute_force_in_depth_order():
    grid = TileGrid(70, 45, 16)
    means2d, radii, depths, visible = _random_footprints(0, 300, 70, 45)
    isect = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, 20000)
    assert int(isect.overflow) == 0
    order = np.asarray(isect.order)
    pairs = np.asarray(isect.pair_gaussians)
    expected = _brute_force(means2d, radii, depths, visible, grid)
    for t in range(grid.num_tiles):
        got = order[pairs[isect.tile_starts[t]:isect.tile_ends[t]]].tolist()
        assert got == expected[t], t
    assert int(isect.num_pairs) == sum(map(len, expected))


@pytest.mark.slow
def test_overflow_drops_the_farthest_pairs_and_counts_them():
    grid = TileGrid(64, 64, 16)
    means2d, radii, depths, visible = _random_footprints(1, 200, 64, 64)
    full = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, 50000)
    cap = int(full.num_pairs) // 2
    small = intersect_tiles(*map(jnp.asarray, (means2d, radii, depths, visible)), grid, cap)
    assert int(small.num_pairs) == cap
    assert int(small.overflow) == int(full.num_pairs) - cap
    # What survives is the front part of every tile's list.
    order = np.asarray(full.order)
    for t in range(grid.num_tiles):
        a = order[np.asarray(full.pair_gaussians)[full.tile_starts[t]:full.tile_ends[t]]]
        b = order[np.asarray(small.pair_gaussians)[small.tile_starts[t]:small.tile_ends[t]]]
        assert a[: len(b)].tolist() == b.tolist()
