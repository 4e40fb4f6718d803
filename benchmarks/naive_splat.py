"""A deliberately naive tile renderer: the baseline the splatter is measured against.

Every tile takes the K nearest Gaussians whose footprint box touches it
(``lax.top_k`` over all G), composites them densely ([S, K] alphas, a
``cumprod`` for transmittance) and is differentiated by plain autodiff, which
stores every intermediate. ``jax.vmap`` over tiles. It truncates at K
Gaussians per tile and has no early termination, so it is neither exact nor
fast; it exists only so the benchmark can report side-by-side ratios.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cusgs_jax.splat.project import project_gaussians


def naive_rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height,
                    tile_size=16, top_k=256):
    """[H, W, C] image; same conventions as ``cusgs_jax.splat.rasterize``."""
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height)
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    ty, tx = jnp.divmod(jnp.arange(tiles_x * tiles_y), tiles_x)
    lo = proj.means2d - proj.radii
    hi = proj.means2d + proj.radii
    iy, ix = jnp.divmod(jnp.arange(tile_size * tile_size), tile_size)

    def tile(tile_x, tile_y):
        x0, y0 = tile_x * tile_size, tile_y * tile_size
        touches = (proj.visible & (hi[:, 0] > x0) & (lo[:, 0] < x0 + tile_size)
                   & (hi[:, 1] > y0) & (lo[:, 1] < y0 + tile_size))
        score = jnp.where(touches, -proj.depths, -jnp.inf)
        top, idx = jax.lax.top_k(score, top_k)
        ok = jnp.isfinite(top)
        px = x0 + ix + 0.5
        py = y0 + iy + 0.5
        dx = proj.means2d[idx, 0][None] - px[:, None]
        dy = proj.means2d[idx, 1][None] - py[:, None]
        a, b, c = (proj.conics[idx, i][None] for i in range(3))
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = jnp.minimum(0.999, proj.opacities[idx][None] * jnp.exp(-sigma))
        alpha = jnp.where(ok[None] & (sigma >= 0) & (alpha >= 1 / 255), alpha, 0.0)
        trans = jnp.cumprod(1.0 - alpha, axis=-1)
        before = jnp.concatenate([jnp.ones_like(trans[:, :1]), trans[:, :-1]], axis=-1)
        return (alpha * before) @ colors[idx]

    out = jax.vmap(tile)(tx, ty)
    img = out.reshape(tiles_y, tiles_x, tile_size, tile_size, -1)
    img = jnp.moveaxis(img, 2, 1).reshape(tiles_y * tile_size, tiles_x * tile_size, -1)
    return img[:height, :width]
