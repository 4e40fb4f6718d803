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


def _random_tiles(rng, grid, num, opacity_high=0.95):
    means2d = jnp.asarray(rng.uniform(0, [grid.width, grid.height], (num, 2)))
    conics = jnp.asarray(np.stack([rng.uniform(0.05, 0.5, num), rng.uniform(-0.02, 0.02, num),
                                   rng.uniform(0.05, 0.5, num)], -1))
    opacities = jnp.asarray(rng.uniform(0.05, opacity_high, num))  # high enough to terminate some pixels
    pairs = jnp.tile(jnp.arange(num, dtype=jnp.int32), grid.num_tiles)
    starts = jnp.arange(grid.num_tiles, dtype=jnp.int32) * num
    return means2d, conics, opacities, pairs, starts, starts + num


def test_sparse_channels_equal_dense_ones_at_the_listed_pixels(x64):
    """Channels composited only at listed pixels (``sparse``/``sparse_slots``) give the dense compositor's values
    there, and the same gradients for a loss that reads only those pixels (float64, pixels terminating)."""
    rng = np.random.default_rng(3)
    grid = TileGrid(20, 12, 8)
    num, q = 30, 5
    means2d, conics, opacities, pairs, starts, ends = _random_tiles(rng, grid, num)
    rgbd = jnp.asarray(rng.uniform(0, 1, (num, 4)))
    extra = jnp.asarray(rng.normal(size=(num, q)))
    listed = [rng.choice(64, size=k, replace=False) for k in (3, 1, 0, 5, 2, 4)]  # some tiles list none
    k_max = max(len(x) for x in listed)
    slots = np.full((grid.num_tiles, k_max), 64, np.int32)
    for t, x in enumerate(listed):
        slots[t, :len(x)] = x
    slots = jnp.asarray(slots)
    mask = np.zeros((grid.num_tiles, 64), bool)
    for t, x in enumerate(listed):
        mask[t, x] = True
    wc = jnp.asarray(rng.normal(size=(grid.num_tiles, 64, 4)))
    wq = jnp.asarray(rng.normal(size=(grid.num_tiles, 64, q)) * mask[..., None])  # read at listed pixels only
    wt = jnp.asarray(rng.normal(size=(grid.num_tiles, 64)))

    def dense(m, c, o, f, e):
        out = composite_tiles(grid, 4, 2, m, c, o, jnp.concatenate([f, e], -1), pairs, starts, ends)
        return (jnp.sum(out.colors[..., :4] * wc) + jnp.sum(out.colors[..., 4:] * wq)
                + jnp.sum(out.transmittance * wt)), out

    def sparse(m, c, o, f, e):
        out = composite_tiles(grid, 4, 2, m, c, o, f, pairs, starts, ends, e, slots)
        at = jnp.take_along_axis(wq, jnp.minimum(slots, 63)[..., None], axis=1) * (slots < 64)[..., None]
        return (jnp.sum(out.colors * wc) + jnp.sum(out.sparse * at) + jnp.sum(out.transmittance * wt)), out

    args = (means2d, conics, opacities, rgbd, extra)
    (_, d_out), (_, s_out) = dense(*args), sparse(*args)
    assert (np.asarray(d_out.n_contrib) < num).any(), "some pixels must terminate early"
    for t, x in enumerate(listed):
        np.testing.assert_allclose(s_out.sparse[t, :len(x)], d_out.colors[t, x, 4:], rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(s_out.sparse[t, len(x):], 0.0)
    np.testing.assert_allclose(s_out.colors, d_out.colors[..., :4], rtol=1e-12, atol=1e-14)  # summed apart
    np.testing.assert_array_equal(s_out.transmittance, d_out.transmittance)
    g_dense = jax.grad(lambda *a: dense(*a)[0], argnums=(0, 1, 2, 3, 4))(*args)
    g_sparse = jax.grad(lambda *a: sparse(*a)[0], argnums=(0, 1, 2, 3, 4))(*args)
    for name, a, b in zip(("means2d", "conics", "opacities", "features", "sparse"), g_dense, g_sparse):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12, err_msg=name)
    # jitted (float32 would differ only by rounding; here float64): the same as eager
    g_jit = jax.jit(jax.grad(lambda *a: sparse(*a)[0], argnums=(0, 1, 2, 3, 4)))(*args)
    for a, b in zip(g_sparse, g_jit):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-14)
