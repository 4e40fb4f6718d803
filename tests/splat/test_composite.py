"""composite_tiles: custom VJP against autodiff of a dense float64 composite."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.splat.composite import composite_tiles
from cusgs_jax.splat.tiles import TileGrid


def _dense(means2d, conics, opacities, features, grid):
    """Plain differentiable composite of all (depth-sorted) Gaussians at every pixel."""
    iy, ix = np.mgrid[: grid.height, : grid.width]
    px, py = ix.ravel() + 0.5, iy.ravel() + 0.5
    dx = means2d[None, :, 0] - px[:, None]
    dy = means2d[None, :, 1] - py[:, None]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = jnp.minimum(0.999, opacities * jnp.exp(-sigma))
    alpha = jnp.where((sigma >= 0) & (alpha >= 1 / 255), alpha, 0.0)
    trans = jnp.cumprod(1 - alpha, axis=1)
    before = jnp.concatenate([jnp.ones_like(trans[:, :1]), trans[:, :-1]], axis=1)
    return (alpha * before) @ features, trans[:, -1]


def test_custom_vjp_matches_dense_autodiff(x64):
    rng = np.random.default_rng(0)
    grid = TileGrid(20, 12, 8)
    num = 25
    means2d = jnp.asarray(rng.uniform(0, [20, 12], (num, 2)))
    conics = jnp.asarray(np.stack([rng.uniform(0.05, 0.5, num), rng.uniform(-0.02, 0.02, num),
                                   rng.uniform(0.05, 0.5, num)], -1))
    opacities = jnp.asarray(rng.uniform(0.05, 0.6, num))  # low enough never to terminate
    features = jnp.asarray(rng.uniform(0, 1, (num, 3)))
    # every tile lists every Gaussian (depth order = index order)
    pairs = jnp.tile(jnp.arange(num, dtype=jnp.int32), grid.num_tiles)
    starts = jnp.arange(grid.num_tiles, dtype=jnp.int32) * num
    ends = starts + num
    wc = jnp.asarray(rng.normal(size=(grid.num_tiles, 64, 3)))
    wt = jnp.asarray(rng.normal(size=(grid.num_tiles, 64)))

    def ours(m, c, o, f):
        out = composite_tiles(grid, 8, 2, m, c, o, f, pairs, starts, ends)
        return jnp.sum(out.colors * wc) + jnp.sum(out.transmittance * wt)

    def to_tiles(img):
        h = img.reshape(grid.tiles_y, 8, grid.tiles_x, 8, -1)
        return jnp.moveaxis(h, 2, 1).reshape(grid.num_tiles, 64, -1)

    def dense(m, c, o, f):
        col, tr = _dense(m, c, o, f, TileGrid(24, 16, 8))  # padded to whole tiles
        return jnp.sum(to_tiles(col.reshape(16, 24, 3)) * wc) + jnp.sum(to_tiles(tr.reshape(16, 24, 1))[..., 0] * wt
                                                                        * _inside(grid))

    def _inside(grid):
        iy, ix = np.mgrid[:16, :24]
        return to_tiles(jnp.asarray((ix < 20) & (iy < 12), jnp.float64).reshape(16, 24, 1))[..., 0]

    # Padding pixels hold T = 1 in ours and are skipped; mask them in the dense one.
    wc = wc * _inside(grid)[..., None]
    args = (means2d, conics, opacities, features)
    np.testing.assert_allclose(ours(*args), dense(*args) + jnp.sum(wt * (1 - _inside(grid))), rtol=1e-10)
    g_ours = jax.grad(ours, argnums=(0, 1, 2, 3))(*args)
    g_dense = jax.grad(dense, argnums=(0, 1, 2, 3))(*args)
    for a, b in zip(g_ours, g_dense):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)
