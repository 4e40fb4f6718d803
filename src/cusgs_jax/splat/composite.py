"""Front-to-back alpha compositing over tiles, with a memory-light custom VJP.

Shapes: G depth-sorted Gaussians, P pair slots, T tiles, S = tile_size² pixels
per tile, B Gaussians per chunk, C channels.

Forward (gsplat ``rasterize_to_pixels``): every tile walks its depth-sorted run
of Gaussians ``B`` at a time. Tiles are scheduled on M *lanes* (a static
number, like GPU thread blocks): a lane composites one tile until the tile's
list is exhausted or all its pixels have terminated, writes the tile out and
takes the next unprocessed tile, longest first. So the work skipped after early
termination is really skipped, and one long tile no longer holds every other
tile in lockstep. Per pixel and Gaussian (docs/rasterizer.md#compositing)::

    σ = ½(a dx² + c dy²) + b dx dy        skip if σ < 0
    α = min(0.999, o e^{−σ})               skip if α < 1/255
    stop before the Gaussian that brings T to ≤ 1e-4
    C += c α T ;  T *= (1 − α)

Backward: nothing per Gaussian–pixel pair is stored. The forward saves per
pixel only the foreground colour, the final transmittance and the index one
past the last composited Gaussian; the backward walks the same chunks again on
lanes (each tile only up to its pixels' largest last index), recomputing α and
T, and uses

    ∂L/∂c_k = g α_k T_k
    ∂L/∂α_k = T_k (g·c_k) − S_k / (1 − α_k),
    S_k     = Σ_{j>k} (g·c_j) α_j T_j + T_final ∂L/∂T_final
            = g·C_fg − Σ_{j≤k} (g·c_j) α_j T_j + T_final ∂L/∂T_final,

the suffix sum obtained in the same front-to-back order from the saved total
(gsplat's backward walks back to front and divides T by (1 − α) instead).

The chain rule through σ needs, per pair, Σ_s ∂L/∂σ times dx, dy, dx², dx dy, dy² over the
tile's pixels. With the pixel at (lx, ly) from the tile's top-left corner and the mean at
(u, v) from it, dx = u − lx and dy = v − ly, so these are polynomials in (u, v) whose
coefficients are the moments Σ_s ∂L/∂σ · {1, lx, ly, lx², lx ly, ly²} — one matmul of the
chunk's ∂L/∂σ against a [S, 6] basis shared by every tile (``_pixel_basis``).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.scan import running_sum
from cusgs_jax.splat.tiles import TileGrid
from cusgs_jax.precision import HIGHEST

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
      sparse: [T, K, Q] Σ c α T of the sparse channels at each tile's K listed pixels (``sparse_slots``),
        or None when there are none.
    """

    colors: jax.Array
    transmittance: jax.Array
    n_contrib: jax.Array
    last: jax.Array
    significance: jax.Array
    hits: jax.Array
    sparse: jax.Array | None = None


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
    """One chunk of B Gaussians for every lane, pixel axis last ([M, B, S])."""

    gid: jax.Array  # [M, B] sorted-Gaussian index
    in_range: jax.Array  # [M, B] slot belongs to the lane's tile
    mean: jax.Array  # [M, B, 2]
    conic: jax.Array  # [M, B, 3]
    opacity: jax.Array  # [M, B]
    dx: jax.Array  # [M, B, S] mean − pixel
    dy: jax.Array
    gauss: jax.Array  # [M, B, S] e^{−σ}
    alpha: jax.Array  # [M, B, S] min(0.999, o e^{−σ})
    unclamped: jax.Array  # [M, B, S] o e^{−σ} < 0.999
    valid: jax.Array  # [M, B, S] σ ≥ 0 and α ≥ 1/255 (and a real pixel)


def _chunk(tile, k0, chunk, records, pairs, starts, ends, pixels, inside) -> _Chunk:
    """Gather chunk ``[k0, k0 + B)`` of each lane's tile and evaluate its Gaussians.

    Args:
      tile: [M] tile per lane (``num_tiles`` = idle lane).
      k0: [M] chunk start within the tile's run.
      records: [G, 6] = (mean x, mean y, conic a, b, c, opacity), so that a
        single gather fetches everything.
    """
    num_tiles = starts.shape[0]
    active = tile < num_tiles
    safe = jnp.minimum(tile, num_tiles - 1)
    slots = starts[safe][:, None] + k0[:, None] + jnp.arange(chunk, dtype=jnp.int32)[None, :]
    in_range = (slots < ends[safe][:, None]) & active[:, None]
    gid = pairs[jnp.minimum(slots, pairs.shape[0] - 1)]
    rec = records[gid]  # [M, B, 6]
    mean, conic, opacity = rec[..., 0:2], rec[..., 2:5], rec[..., 5]
    pix = pixels[safe]  # [M, S, 2]
    dx = mean[..., 0:1] - pix[:, None, :, 0]
    dy = mean[..., 1:2] - pix[:, None, :, 1]
    a, b, c = conic[..., 0:1], conic[..., 1:2], conic[..., 2:3]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    gauss = jnp.exp(-jnp.maximum(sigma, 0.0))
    raw = opacity[..., None] * gauss
    alpha = jnp.minimum(MAX_ALPHA, raw)
    valid = (in_range[..., None] & inside[safe][:, None, :]
             & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD))
    return _Chunk(gid, in_range, mean, conic, opacity, dx, dy, gauss, alpha,
                  raw < MAX_ALPHA, valid)


MAX_LANES = 320


def default_lanes(num_tiles: int) -> int:
    """Lanes used when not given: a quarter of the tiles, at least 32 and at most ``MAX_LANES``
    (capped by the tile count).

    Every loop iteration materialises a few [M, B, S] arrays; past ~300 lanes they fall out of
    the CPU's caches and the loop becomes memory-bound: at 640×480 (4800 tiles of 8²) fwd+bwd
    took 2.03 s with 1200 lanes against 1.35 s with 300 (``benchmarks/splat_bench.py``-style
    measurement of the 60-view target scene's first view, 937k pairs); at 160×120 (300 tiles)
    75 lanes were fastest (68 ms against 99 ms with 32 and 129 ms with 150).
    """
    return max(1, min(num_tiles, MAX_LANES, max(32, num_tiles // 4)))


class _Schedule(NamedTuple):
    """Longest-first queue of the tiles with work."""

    order: jax.Array  # [T] tiles by decreasing work, then index
    num_work: jax.Array  # [] tiles with any work


def _schedule(work: jax.Array) -> _Schedule:
    tiles = jnp.arange(work.shape[0], dtype=jnp.int32)
    _, order = jax.lax.sort((-work, tiles), num_keys=1, is_stable=True)
    return _Schedule(order, jnp.sum(work > 0).astype(jnp.int32))


def _next_tiles(schedule: _Schedule, tile, finished, cursor):
    """Hand finished lanes the next tiles of the queue (idle sentinel T when empty).

    Returns:
      (tile [M], cursor []) updated.
    """
    num_tiles = schedule.order.shape[0]
    position = cursor + running_sum(finished) - 1
    fresh = jnp.where(position < schedule.num_work,
                      schedule.order[jnp.clip(position, 0, num_tiles - 1)], num_tiles)
    return jnp.where(finished, fresh, tile), cursor + jnp.sum(finished, dtype=jnp.int32)


def _initial_lanes(schedule: _Schedule, lanes: int):
    num_tiles = schedule.order.shape[0]
    first = jnp.arange(lanes, dtype=jnp.int32)
    tile = jnp.where(first < schedule.num_work, schedule.order[jnp.minimum(first, num_tiles - 1)], num_tiles)
    return tile, jnp.minimum(schedule.num_work, lanes).astype(jnp.int32)


def _running_product(factors: jax.Array, start: jax.Array):
    """Exclusive and inclusive running products along the chunk axis.

    An unrolled loop over B slices of [T, S]: on CPU this fuses into one pass
    and is several times faster than ``jnp.cumprod`` (a reduce_window).

    Args:
      factors: [T, B, S]; start: [T, S].
    Returns:
      (before [T, B, S], after [T, B, S]) with ``before[:, k] = start ·
      Π_{j<k} factors[:, j]`` and ``after[:, k] = before[:, k] · factors[:, k]``.
    """
    before, after = [], []
    running = start
    for k in range(factors.shape[1]):
        before.append(running)
        running = running * factors[:, k]
        after.append(running)
    return jnp.stack(before, axis=1), jnp.stack(after, axis=1)


def _running_sum(terms: jax.Array) -> jax.Array:
    """Inclusive running sum along the chunk axis of [T, B, S] (unrolled)."""
    out, running = [], jnp.zeros_like(terms[:, 0])
    for k in range(terms.shape[1]):
        running = running + terms[:, k]
        out.append(running)
    return jnp.stack(out, axis=1)


def _fold_kept(keep, a, k0, trans, n_contrib, last):
    """Fold one chunk's composited Gaussians into each pixel's running state (unrolled over B).

    ``trans · Π_kept (1 − α)``, ``n_contrib + #kept`` and ``last`` = one past the slot of the
    last kept Gaussian, for [M, B, S] ``keep``/``a``, [M] chunk starts ``k0`` and [M, S] state.
    Reductions over the middle (chunk) axis of [M, B, S] — above all the int32 max behind
    ``last`` — are slow on CPU; B elementwise selects fuse into one pass.
    """
    for k in range(keep.shape[1]):
        kept = keep[:, k]
        trans = jnp.where(kept, trans * (1.0 - a[:, k]), trans)
        n_contrib = n_contrib + kept.astype(jnp.int32)
        last = jnp.where(kept, (k0 + (k + 1))[:, None], last)  # later slots are larger: the last kept wins
    return trans, n_contrib, last


SMALL_CHANNELS = 8  # up to this many channels the per-lane contractions are written out channel by channel


def _weighted_sum(weight: jax.Array, feat: jax.Array) -> jax.Array:
    """Σ_b weight[m, b, s] · feat[m, b, c] → [M, S, C].

    For few channels (RGB + depth) a batched ``dot_general`` of M tiny matrices is slow on CPU;
    one multiply-reduce over a broadcast [M, B, C, S] product is a single fused reduction (one per
    channel was C passes over ``weight``).
    """
    if feat.shape[-1] > SMALL_CHANNELS:
        return jnp.einsum("mbs,mbc->msc", weight, feat, precision=HIGHEST)
    return jnp.moveaxis(jnp.sum(weight[:, :, None, :] * feat[..., None], axis=1), 1, 2)


def _channel_dot(lane_g: jax.Array, feat: jax.Array) -> jax.Array:
    """Σ_c lane_g[m, s, c] · feat[m, b, c] → [M, B, S] (see :func:`_weighted_sum`)."""
    if feat.shape[-1] > SMALL_CHANNELS:
        return jnp.einsum("msc,mbc->mbs", lane_g, feat, precision=HIGHEST)
    total = lane_g[:, None, :, 0] * feat[:, :, 0, None]
    for c in range(1, feat.shape[-1]):
        total = total + lane_g[:, None, :, c] * feat[:, :, c, None]
    return total


def _pixel_sum(weight: jax.Array, lane_g: jax.Array) -> jax.Array:
    """Σ_s weight[m, b, s] · lane_g[m, s, c] → [M, B, C] (one fused reduction, see :func:`_weighted_sum`)."""
    if lane_g.shape[-1] > SMALL_CHANNELS:
        return jnp.einsum("mbs,msc->mbc", weight, lane_g, precision=HIGHEST)
    return jnp.sum(weight[:, :, None, :] * jnp.moveaxis(lane_g, 1, 2)[:, None], axis=-1)


def _pixel_basis(tile_size: int, dtype) -> jax.Array:
    """[S, 6] the monomials {1, lx, ly, lx², lx ly, ly²} of each pixel centre from its tile's corner.

    The same for every tile, so the backward's per-pair pixel moments of a whole chunk are one
    plain [M·2·B, S] × [S, 6] matmul rather than six reductions over [M, B, S] products.
    """
    iy, ix = np.divmod(np.arange(tile_size * tile_size), tile_size)
    lx, ly = ix + 0.5, iy + 0.5
    return jnp.asarray(np.stack([np.ones_like(lx), lx, ly, lx * lx, lx * ly, ly * ly], axis=-1), dtype)


def _slot_onehot(slots: jax.Array, num_pixels: int, dtype) -> jax.Array:
    """[M, K, S] 1 where pixel s is a lane's k-th listed pixel (``slots`` [M, K], S = unused entry)."""
    return (jnp.arange(num_pixels, dtype=jnp.int32)[None, None, :] == slots[:, :, None]).astype(dtype)


def _at_slots(x: jax.Array, slots: jax.Array) -> jax.Array:
    """[M, B, S] (or [M, B, R, S]) read at each lane's K listed pixels: [M, B, K] ([M, B, R, K]), one gather;
    ``slots`` [M, K] (S = unused entry, read as 0)."""
    num_pixels = x.shape[-1]
    index = jnp.minimum(slots, num_pixels - 1)
    index = index[:, None, :] if x.ndim == 3 else index[:, None, None, :]
    taken = jnp.take_along_axis(x, jnp.broadcast_to(index, x.shape[:-1] + slots.shape[1:]), axis=-1)
    listed = slots < num_pixels
    listed = listed[:, None, :] if x.ndim == 3 else listed[:, None, None, :]
    return jnp.where(listed, taken, jnp.zeros((), x.dtype))


def _from_slots(values: jax.Array, onehot: jax.Array) -> jax.Array:
    """The transpose of :func:`_at_slots`: [M, B, K] values placed at their pixels of [M, B, S] (the K listed
    pixels of a tile are distinct), as K fused multiply-adds."""
    out = values[:, :, 0, None] * onehot[:, None, 0, :]
    for k in range(1, values.shape[2]):
        out = out + values[:, :, k, None] * onehot[:, None, k, :]
    return out


def _records(means2d, conics, opacities):
    return jnp.concatenate([means2d, conics, opacities[:, None]], axis=-1)


def _forward(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends,
             sparse=None, sparse_slots=None) -> Composite:
    pixels, inside = pixel_centers(grid, means2d.dtype)
    num_tiles, num_pixels = pixels.shape[:2]
    num_gaussians, channels = features.shape
    dtype = means2d.dtype
    records = _records(means2d, conics, opacities)
    lengths = ends - starts
    schedule = _schedule(lengths)
    lanes = min(lanes, num_tiles)
    ones, zeros_i = jnp.ones((lanes, num_pixels), dtype), jnp.zeros((lanes, num_pixels), jnp.int32)
    inside_pad = jnp.concatenate([inside, jnp.zeros((1, num_pixels), bool)])
    has_sparse = sparse is not None
    if has_sparse:
        num_listed, sparse_channels = sparse_slots.shape[1], sparse.shape[1]
        slots_pad = jnp.concatenate([sparse_slots, jnp.full((1, num_listed), num_pixels, jnp.int32)])

    def cond(state):
        return jnp.any(state[0] < num_tiles)

    def body(state):
        tile, k0, cursor, trans, done, color, n_contrib, last, out, stats, acc = state  # acc: None without sparse
        ch = _chunk(tile, k0, chunk, records, pairs, starts, ends, pixels, inside)
        a = jnp.where(ch.valid, ch.alpha, 0.0)
        t_before, t_after = _running_product(1.0 - a, trans)
        keep = ch.valid & (t_after > TRANSMITTANCE_STOP) & ~done[:, None, :]
        weight = jnp.where(keep, a * t_before, 0.0)
        color = color + _weighted_sum(weight, features[ch.gid])
        if has_sparse:  # the sparse channels at the tile's listed pixels only: [M, B, K] × [M, B, Q]
            weight_k = _at_slots(weight, slots_pad[tile])
            acc = acc + jnp.einsum("mbk,mbq->mkq", weight_k, sparse[ch.gid], precision=HIGHEST)
        done = done | jnp.any(ch.valid & (t_after <= TRANSMITTANCE_STOP), axis=1)
        trans, n_contrib, last = _fold_kept(keep, a, k0, trans, n_contrib, last)
        # LightGaussian significance Σ o·T and hit counts, per pair then per Gaussian.
        sig = jnp.sum(jnp.where(keep, ch.opacity[..., None] * t_before, 0.0), axis=-1)
        hit = jnp.sum(keep, axis=-1).astype(dtype)
        pair_stats = jnp.where(ch.in_range[..., None], jnp.stack([sig, hit], axis=-1), 0.0)
        stats = stats.at[ch.gid].add(pair_stats)
        # lanes whose tile is exhausted or fully terminated write it out and move on
        k0 = k0 + chunk
        safe = jnp.minimum(tile, num_tiles - 1)
        finished = (tile < num_tiles) & ((k0 >= lengths[safe]) | jnp.all(done, axis=-1))
        target = jnp.where(finished, tile, num_tiles)
        values = (color, trans, n_contrib, last) + ((acc,) if has_sparse else ())
        out = tuple(o.at[target].set(v, mode="drop") for o, v in zip(out, values))
        tile, cursor = _next_tiles(schedule, tile, finished, cursor)
        reset = finished[:, None]
        k0 = jnp.where(finished, 0, k0)
        trans = jnp.where(reset, 1.0, trans)
        done = jnp.where(reset, ~inside_pad[tile], done)
        color = jnp.where(reset[..., None], 0.0, color)
        n_contrib = jnp.where(reset, 0, n_contrib)
        last = jnp.where(reset, 0, last)
        if has_sparse:
            acc = jnp.where(reset[..., None], 0.0, acc)
        return tile, k0, cursor, trans, done, color, n_contrib, last, out, stats, acc

    tile, cursor = _initial_lanes(schedule, lanes)
    out = (
        jnp.zeros((num_tiles, num_pixels, channels), dtype),
        jnp.ones((num_tiles, num_pixels), dtype),
        jnp.zeros((num_tiles, num_pixels), jnp.int32),
        jnp.zeros((num_tiles, num_pixels), jnp.int32),
    ) + ((jnp.zeros((num_tiles, num_listed, sparse_channels), dtype),) if has_sparse else ())
    acc = jnp.zeros((lanes, num_listed, sparse_channels), dtype) if has_sparse else None
    init = (tile, jnp.zeros(lanes, jnp.int32), cursor, ones, ~inside_pad[tile],
            jnp.zeros((lanes, num_pixels, channels), dtype), zeros_i, zeros_i, out,
            jnp.zeros((num_gaussians, 2), dtype), acc)
    state = jax.lax.while_loop(cond, body, init)
    out, stats = state[8], state[9]
    hits = jnp.round(stats[:, 1]).astype(jnp.int32)
    return Composite(*out[:4], stats[:, 0], hits, out[4] if has_sparse else None)


@partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2))
def composite_tiles(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends,
                    sparse=None, sparse_slots=None):
    """Composite depth-sorted Gaussians into tiles.

    Args:
      grid: static :class:`TileGrid`.
      chunk: static number of Gaussians a tile processes per loop iteration.
      lanes: static number of tiles processed side by side (see module doc).
      means2d: [G, 2], conics: [G, 3], opacities: [G], features: [G, C] —
        all in front-to-back order.
      pairs: [P] int32 sorted-Gaussian index per slot, grouped by tile.
      starts, ends: [T] int32 each tile's slot range.
      sparse: [G, Q] or None — channels composited only at the pixels ``sparse_slots`` lists (what a loss
        that reads a few pixels needs, at K/S of the work of ``features``).
      sparse_slots: [T, K] int32 pixel index within each tile (< S, distinct within a tile; S = unused
        entry), with ``sparse``.
    Returns:
      :class:`Composite`; differentiable in ``colors``, ``transmittance`` and ``sparse``.
    """
    return _forward(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends,
                    sparse, sparse_slots)


def _composite_fwd(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends,
                   sparse=None, sparse_slots=None):
    out = _forward(grid, chunk, lanes, means2d, conics, opacities, features, pairs, starts, ends,
                   sparse, sparse_slots)
    residuals = (means2d, conics, opacities, features, pairs, starts, ends,
                 out.colors, out.transmittance, out.last, sparse, sparse_slots, out.sparse)
    return out, residuals


def _composite_bwd(grid, chunk, lanes, residuals, cotangents):
    (means2d, conics, opacities, features, pairs, starts, ends,
     color_fg, trans_final, last, sparse, sparse_slots, sparse_fg) = residuals
    g_color, g_trans = cotangents.colors, cotangents.transmittance
    has_sparse = sparse is not None
    pixels, inside = pixel_centers(grid, means2d.dtype)
    num_tiles, num_pixels = pixels.shape[:2]
    channels = features.shape[1]
    dtype = means2d.dtype
    records = _records(means2d, conics, opacities)
    # Total Σ_k (g·c_k) α_k T_k and the background-side term of S_k.
    total = jnp.sum(g_color * color_fg, axis=-1)
    tail = trans_final * g_trans
    if has_sparse:  # the sparse channels' share of S_k, at each tile's listed pixels
        g_sparse = cotangents.sparse  # [T, K, Q]
        total_sparse = jnp.sum(g_sparse * sparse_fg, axis=-1)  # [T, K]
        num_listed, sparse_channels = sparse_slots.shape[1], sparse.shape[1]
    need = jnp.max(last, axis=-1)  # [T] slots each tile must revisit
    basis = _pixel_basis(grid.tile_size, dtype)
    tile_origin = pixels[:, 0, :] - 0.5  # [T, 2] each tile's top-left corner
    schedule = _schedule(need)
    lanes = min(lanes, num_tiles)

    def cond(state):
        return jnp.any(state[0] < num_tiles)

    def body(state):
        tile, k0, cursor, trans, prefix, prefix_sparse, grads = state  # prefix_sparse: None without sparse
        safe = jnp.minimum(tile, num_tiles - 1)
        ch = _chunk(tile, k0, chunk, records, pairs, starts, ends, pixels, inside)
        slot = k0[:, None] + jnp.arange(chunk, dtype=jnp.int32)[None, :]
        keep = ch.valid & (slot[..., None] < last[safe][:, None, :])
        a = jnp.where(keep, ch.alpha, 0.0)
        t_before, t_after = _running_product(1.0 - a, trans)
        weight = a * t_before  # zero where not kept
        feat = features[ch.gid]  # [M, B, C]
        lane_g = g_color[safe]  # [M, S, C]
        g_dot_c = _channel_dot(lane_g, feat)
        contrib = g_dot_c * weight
        running = _running_sum(contrib)
        suffix = (total[safe] - prefix + tail[safe])[:, None, :] - running
        d_alpha = t_before * g_dot_c - suffix / (1.0 - a)
        kept = keep & ch.unclamped  # where ∂L/∂α is not zero
        d_alpha = jnp.where(kept, d_alpha, 0.0)
        if has_sparse:  # the same terms for the sparse channels at the K listed pixels, then placed there
            lane_slots = sparse_slots[safe]
            onehot = _slot_onehot(lane_slots, num_pixels, dtype)  # idle lanes keep nothing: zeros
            weight_k, t_before_k, a_k, kept_k = jnp.moveaxis(
                _at_slots(jnp.stack([weight, t_before, a, kept.astype(dtype)], axis=2), lane_slots), 2, 0)
            feat_sparse = sparse[ch.gid]  # [M, B, Q]
            lane_gs = g_sparse[safe]  # [M, K, Q]
            g_dot_k = jnp.einsum("mkq,mbq->mbk", lane_gs, feat_sparse, precision=HIGHEST)
            running_k = _running_sum(g_dot_k * weight_k)
            suffix_k = (total_sparse[safe] - prefix_sparse)[:, None, :] - running_k
            d_alpha_k = t_before_k * g_dot_k - suffix_k / (1.0 - a_k)
            d_alpha_k = jnp.where(kept_k > 0, d_alpha_k, 0.0)
            d_alpha = d_alpha + _from_slots(d_alpha_k, onehot)
            pair_sparse = jnp.einsum("mbk,mkq->mbq", weight_k, lane_gs, precision=HIGHEST)
            prefix_sparse = prefix_sparse + running_k[:, -1]
        d_sigma = -d_alpha * a
        # The σ moments Σ_s dσ·{dx, dy, dx², dx dy, dy²} and Σ_s dα·G from one matmul against the
        # tile-local pixel basis (module doc): dx = u − lx with u the mean from the tile's corner.
        num_lanes, num_slots, num_pix = d_sigma.shape
        left = jnp.stack([d_sigma, d_alpha * ch.gauss], axis=1).reshape(num_lanes * 2 * num_slots, num_pix)
        moments = jnp.dot(left, basis, precision=HIGHEST).reshape(num_lanes, 2, num_slots, 6)
        s0, s1, s2, s3, s4, s5 = (moments[:, 0, :, i] for i in range(6))
        origin = tile_origin[safe]  # [M, 2]
        u = ch.mean[..., 0] - origin[:, None, 0]
        v = ch.mean[..., 1] - origin[:, None, 1]
        sx = u * s0 - s1  # Σ dσ dx
        sy = v * s0 - s2  # Σ dσ dy
        ca, cb, cc = ch.conic[..., 0], ch.conic[..., 1], ch.conic[..., 2]
        pair = jnp.concatenate(
            [
                jnp.stack(
                    [
                        ca * sx + cb * sy,  # ∂σ/∂μx = a dx + b dy
                        cc * sy + cb * sx,  # ∂σ/∂μy = c dy + b dx
                        0.5 * (u * u * s0 - 2.0 * u * s1 + s3),  # ½ Σ dσ dx²
                        u * v * s0 - u * s2 - v * s1 + s4,  # Σ dσ dx dy
                        0.5 * (v * v * s0 - 2.0 * v * s2 + s5),  # ½ Σ dσ dy²
                        moments[:, 1, :, 0],  # Σ dα G
                    ],
                    axis=-1,
                ),
                _pixel_sum(weight, lane_g),
            ] + ([pair_sparse] if has_sparse else []),
            axis=-1,
        )
        grads = grads.at[ch.gid].add(jnp.where(ch.in_range[..., None], pair, 0.0))
        trans = t_after[:, -1]  # trans · Π_b (1 − α_b)
        prefix = prefix + running[:, -1]
        k0 = k0 + chunk
        finished = (tile < num_tiles) & (k0 >= need[safe])
        tile, cursor = _next_tiles(schedule, tile, finished, cursor)
        k0 = jnp.where(finished, 0, k0)
        trans = jnp.where(finished[:, None], 1.0, trans)
        prefix = jnp.where(finished[:, None], 0.0, prefix)
        if has_sparse:
            prefix_sparse = jnp.where(finished[:, None], 0.0, prefix_sparse)
        return tile, k0, cursor, trans, prefix, prefix_sparse, grads

    tile, cursor = _initial_lanes(schedule, lanes)
    extra = sparse_channels if has_sparse else 0
    init = (
        tile, jnp.zeros(lanes, jnp.int32), cursor,
        jnp.ones((lanes, num_pixels), dtype),
        jnp.zeros((lanes, num_pixels), dtype),
        jnp.zeros((lanes, num_listed), dtype) if has_sparse else None,
        jnp.zeros((means2d.shape[0], 6 + channels + extra), dtype),
    )
    grads = jax.lax.while_loop(cond, body, init)[-1]
    g_sparse_in = grads[:, 6 + channels:] if has_sparse else None
    return (grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:6 + channels], None, None, None,
            g_sparse_in, None)


composite_tiles.defvjp(_composite_fwd, _composite_bwd)
