"""Front-to-back alpha compositing over tiles, with a memory-light custom VJP.

Shapes: G depth-sorted Gaussians, P pair slots, T tiles, S = tile_size² pixels
per tile, B Gaussians per chunk, C channels.

Forward (gsplat ``rasterize_to_pixels``): every tile walks its depth-sorted run
of Gaussians ``B`` at a time; all tiles advance together inside one
``lax.while_loop`` that stops as soon as every tile is exhausted or every pixel
has terminated, so work after early termination is skipped. Per pixel and
Gaussian (DESIGN.md §2)::

    σ = ½(a dx² + c dy²) + b dx dy        skip if σ < 0
    α = min(0.999, o e^{−σ})               skip if α < 1/255
    stop before the Gaussian that brings T to ≤ 1e-4
    C += c α T ;  T *= (1 − α)

Backward: nothing per Gaussian–pixel pair is stored. The forward saves per
pixel only the foreground colour, the final transmittance and the index one
past the last composited Gaussian; the backward walks the same chunks again,
recomputing α and T, and uses

    ∂L/∂c_k = g α_k T_k
    ∂L/∂α_k = T_k (g·c_k) − S_k / (1 − α_k),
    S_k     = Σ_{j>k} (g·c_j) α_j T_j + T_final ∂L/∂T_final
            = g·C_fg − Σ_{j≤k} (g·c_j) α_j T_j + T_final ∂L/∂T_final,

the suffix sum obtained in the same front-to-back order from the saved total
(gsplat's backward walks back to front and divides T by (1 − α) instead).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.splat.tiles import TileGrid

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.999
TRANSMITTANCE_STOP = 1e-4


class Composite(NamedTuple):
    """Per-tile compositing result.

    Attributes:
      colors: [T, S, C] Σ c α T (background not added).
      transmittance: [T, S] final T.
      n_contrib: [T, S] int32 number of Gaussians composited.
      last: [T, S] int32 one past the slot (within the tile) of the last one.
      significance: [G] Σ over composited pixels of o·T (not differentiable).
      hits: [G] int32 number of pixels each Gaussian was composited into.
    """

    colors: jax.Array
    transmittance: jax.Array
    n_contrib: jax.Array
    last: jax.Array
    significance: jax.Array
    hits: jax.Array


def pixel_centers(grid: TileGrid, dtype=jnp.float32) -> tuple[jax.Array, jax.Array]:
    """Pixel sample positions ``(j + 0.5, i + 0.5)`` per tile.

    Returns:
      centers: [T, S, 2] (x, y).
      inside: [T, S] bool, False for the padding of partial edge tiles.
    """
    ts = grid.tile_size
    iy, ix = np.divmod(np.arange(ts * ts), ts)
    ty, tx = np.divmod(np.arange(grid.num_tiles), grid.tiles_x)
    px = tx[:, None] * ts + ix[None, :]
    py = ty[:, None] * ts + iy[None, :]
    inside = (px < grid.width) & (py < grid.height)
    centers = np.stack([px + 0.5, py + 0.5], axis=-1)
    return jnp.asarray(centers, dtype=dtype), jnp.asarray(inside)


class _Chunk(NamedTuple):
    gid: jax.Array  # [T, B] sorted-Gaussian index
    in_range: jax.Array  # [T, B]
    dx: jax.Array  # [T, S, B]
    dy: jax.Array
    conic: jax.Array  # [T, B, 3]
    opacity: jax.Array  # [T, B]
    gauss: jax.Array  # [T, S, B] e^{−σ}
    alpha: jax.Array  # [T, S, B] clamped
    unclamped: jax.Array  # [T, S, B]
    valid: jax.Array  # [T, S, B] passes σ ≥ 0 and α ≥ 1/255


def _chunk(k0, chunk, means2d, conics, opacities, pairs, starts, ends, pixels, inside) -> _Chunk:
    slots = starts[:, None] + k0 + jnp.arange(chunk, dtype=jnp.int32)[None, :]
    in_range = slots < ends[:, None]
    gid = pairs[jnp.minimum(slots, pairs.shape[0] - 1)]
    mean = means2d[gid]
    conic = conics[gid]
    opacity = opacities[gid]
    dx = mean[:, None, :, 0] - pixels[:, :, None, 0]
    dy = mean[:, None, :, 1] - pixels[:, :, None, 1]
    a, b, c = (conic[:, None, :, i] for i in range(3))
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    gauss = jnp.exp(-jnp.maximum(sigma, 0.0))
    raw = opacity[:, None, :] * gauss
    alpha = jnp.minimum(MAX_ALPHA, raw)
    valid = (in_range[:, None, :] & inside[:, :, None]
             & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD))
    return _Chunk(gid, in_range, dx, dy, conic, opacity, gauss, alpha, raw < MAX_ALPHA, valid)


def _exclusive_cumprod(x: jax.Array) -> jax.Array:
    """Exclusive cumulative product along the last axis."""
    inclusive = jnp.cumprod(x, axis=-1)
    return jnp.concatenate([jnp.ones_like(x[..., :1]), inclusive[..., :-1]], axis=-1), inclusive


def _forward(grid, chunk, means2d, conics, opacities, features, pairs, starts, ends) -> Composite:
    pixels, inside = pixel_centers(grid, means2d.dtype)
    num_tiles, num_pixels = pixels.shape[:2]
    num_gaussians, channels = features.shape
    dtype = means2d.dtype
    lengths = ends - starts
    max_length = jnp.max(lengths) if num_tiles else jnp.int32(0)

    def cond(state):
        k0, _, done, *_ = state
        active = (k0 < lengths) & ~jnp.all(done | ~inside, axis=-1)
        return (k0 < max_length) & jnp.any(active)

    def body(state):
        k0, trans, done, color, n_contrib, last, significance, hits = state
        ch = _chunk(k0, chunk, means2d, conics, opacities, pairs, starts, ends, pixels, inside)
        a = jnp.where(ch.valid, ch.alpha, 0.0)
        before, after = _exclusive_cumprod(1.0 - a)
        t_before = trans[..., None] * before
        t_after = trans[..., None] * after
        keep = ch.valid & (t_after > TRANSMITTANCE_STOP) & ~done[..., None]
        weight = jnp.where(keep, a * t_before, 0.0)
        color = color + jnp.einsum("tsb,tbc->tsc", weight, features[ch.gid])
        trans = trans * jnp.prod(jnp.where(keep, 1.0 - a, 1.0), axis=-1)
        done = done | jnp.any(ch.valid & (t_after <= TRANSMITTANCE_STOP), axis=-1)
        n_contrib = n_contrib + jnp.sum(keep, axis=-1, dtype=jnp.int32)
        slot = k0 + jnp.arange(1, chunk + 1, dtype=jnp.int32)
        last = jnp.maximum(last, jnp.max(jnp.where(keep, slot, 0), axis=-1))
        sig = jnp.sum(jnp.where(keep, ch.opacity[:, None, :] * t_before, 0.0), axis=1)
        significance = significance.at[ch.gid].add(jnp.where(ch.in_range, sig, 0.0))
        hit = jnp.sum(keep, axis=1, dtype=jnp.int32)
        hits = hits.at[ch.gid].add(jnp.where(ch.in_range, hit, 0))
        return k0 + chunk, trans, done, color, n_contrib, last, significance, hits

    init = (
        jnp.int32(0),
        jnp.ones((num_tiles, num_pixels), dtype),
        jnp.zeros((num_tiles, num_pixels), bool),
        jnp.zeros((num_tiles, num_pixels, channels), dtype),
        jnp.zeros((num_tiles, num_pixels), jnp.int32),
        jnp.zeros((num_tiles, num_pixels), jnp.int32),
        jnp.zeros((num_gaussians,), dtype),
        jnp.zeros((num_gaussians,), jnp.int32),
    )
    _, trans, _, color, n_contrib, last, significance, hits = jax.lax.while_loop(cond, body, init)
    return Composite(color, trans, n_contrib, last, significance, hits)


@partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def composite_tiles(grid, chunk, means2d, conics, opacities, features, pairs, starts, ends):
    """Composite depth-sorted Gaussians into tiles.

    Args:
      grid: static :class:`TileGrid`.
      chunk: static number of Gaussians a tile processes per loop iteration.
      means2d: [G, 2], conics: [G, 3], opacities: [G], features: [G, C] —
        all in front-to-back order.
      pairs: [P] int32 sorted-Gaussian index per slot, grouped by tile.
      starts, ends: [T] int32 each tile's slot range.
    Returns:
      :class:`Composite`; differentiable in ``colors`` and ``transmittance``.
    """
    return _forward(grid, chunk, means2d, conics, opacities, features, pairs, starts, ends)


def _composite_fwd(grid, chunk, means2d, conics, opacities, features, pairs, starts, ends):
    out = _forward(grid, chunk, means2d, conics, opacities, features, pairs, starts, ends)
    residuals = (means2d, conics, opacities, features, pairs, starts, ends,
                 out.colors, out.transmittance, out.last)
    return out, residuals


def _composite_bwd(grid, chunk, residuals, cotangents):
    (means2d, conics, opacities, features, pairs, starts, ends,
     color_fg, trans_final, last) = residuals
    g_color, g_trans = cotangents.colors, cotangents.transmittance
    pixels, inside = pixel_centers(grid, means2d.dtype)
    num_tiles, num_pixels = pixels.shape[:2]
    dtype = means2d.dtype
    # Total Σ_k (g·c_k) α_k T_k and the background-side term of S_k.
    total = jnp.sum(g_color * color_fg, axis=-1)
    tail = trans_final * g_trans
    max_last = jnp.max(last) if num_tiles else jnp.int32(0)

    def cond(state):
        return state[0] < max_last

    def body(state):
        k0, trans, prefix, d_means, d_conics, d_opac, d_feat = state
        ch = _chunk(k0, chunk, means2d, conics, opacities, pairs, starts, ends, pixels, inside)
        slot = k0 + jnp.arange(chunk, dtype=jnp.int32)
        keep = ch.valid & (slot[None, None, :] < last[..., None])
        a = jnp.where(keep, ch.alpha, 0.0)
        before, _ = _exclusive_cumprod(1.0 - a)
        t_before = trans[..., None] * before
        weight = a * t_before  # zero where not kept
        feat = features[ch.gid]  # [T, B, C]
        g_dot_c = jnp.einsum("tsc,tbc->tsb", g_color, feat)
        contrib = g_dot_c * weight
        suffix = (total - prefix)[..., None] - jnp.cumsum(contrib, axis=-1) + tail[..., None]
        d_alpha = t_before * g_dot_c - suffix / (1.0 - a)
        d_alpha = jnp.where(keep & ch.unclamped, d_alpha, 0.0)
        d_sigma = -d_alpha * a
        dx, dy = ch.dx, ch.dy
        ca, cb, cc = (ch.conic[:, None, :, i] for i in range(3))
        pair_d_mean = jnp.stack(
            [jnp.sum(d_sigma * (ca * dx + cb * dy), axis=1),
             jnp.sum(d_sigma * (cc * dy + cb * dx), axis=1)], axis=-1)
        pair_d_conic = jnp.stack(
            [jnp.sum(d_sigma * 0.5 * dx * dx, axis=1),
             jnp.sum(d_sigma * dx * dy, axis=1),
             jnp.sum(d_sigma * 0.5 * dy * dy, axis=1)], axis=-1)
        pair_d_opac = jnp.sum(d_alpha * ch.gauss, axis=1)
        pair_d_feat = jnp.einsum("tsb,tsc->tbc", weight, g_color)
        m = ch.in_range
        d_means = d_means.at[ch.gid].add(jnp.where(m[..., None], pair_d_mean, 0.0))
        d_conics = d_conics.at[ch.gid].add(jnp.where(m[..., None], pair_d_conic, 0.0))
        d_opac = d_opac.at[ch.gid].add(jnp.where(m, pair_d_opac, 0.0))
        d_feat = d_feat.at[ch.gid].add(jnp.where(m[..., None], pair_d_feat, 0.0))
        trans = trans * jnp.prod(1.0 - a, axis=-1)
        prefix = prefix + jnp.sum(contrib, axis=-1)
        return k0 + chunk, trans, prefix, d_means, d_conics, d_opac, d_feat

    init = (
        jnp.int32(0),
        jnp.ones((num_tiles, num_pixels), dtype),
        jnp.zeros((num_tiles, num_pixels), dtype),
        jnp.zeros_like(means2d),
        jnp.zeros_like(conics),
        jnp.zeros_like(opacities),
        jnp.zeros_like(features),
    )
    _, _, _, d_means, d_conics, d_opac, d_feat = jax.lax.while_loop(cond, body, init)
    return d_means, d_conics, d_opac, d_feat, None, None, None


composite_tiles.defvjp(_composite_fwd, _composite_bwd)
