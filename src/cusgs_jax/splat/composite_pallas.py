"""The tile compositor as Pallas kernels: one program per tile, its own list, exact to the JAX path.

Shapes: G depth-sorted Gaussians, P pair slots, T tiles, S = tile_size² pixels per tile,
C channels (padded to Cp, the next power of two, inside the kernels), B Gaussians per unrolled step.

Same inputs, outputs and rules as :func:`cusgs_jax.splat.composite.composite_tiles`
(docs/rasterizer.md#compositing: α = min(0.999, o e^{−σ}), skipped below 1/255 or for σ < 0,
a pixel stops before the Gaussian that brings T to ≤ 1e-4), written the way gsplat's CUDA
rasteriser is (``rasterize_to_pixels_fwd`` / ``_bwd``):

* **forward** — program t walks tile t's sorted list front to back, B Gaussians per step, and
  stops when the list ends or every pixel of the tile has terminated, so a tile's work is bounded
  by its own list (the JAX path's loops run in lockstep lanes). Per pixel it writes the colour,
  the final transmittance, the count and one past the last composited slot; per pair slot the
  significance Σ o·T and the hit count, summed per Gaussian outside the kernel.
* **backward** — program t walks the slots its pixels composited (up to the largest ``last``)
  back to front, from the saved final transmittance: T_k = T_{k+1} / (1 − α_k), and the
  suffix S_k = Σ_{j>k} (g·c_j) α_j T_j + T_final ∂L/∂T_final grows as it goes, so

      ∂L/∂c_k = g α_k T_k ,   ∂L/∂α_k = T_k (g·c_k) − S_k / (1 − α_k)

  (the JAX path gets S_k front to back from the saved total; the two differ by rounding only).
  Per pair slot it writes ∂L/∂(μx, μy, a, b, c, o) and ∂L/∂c, summed per Gaussian outside.

Pair-slot outputs start from zeros (aliased inputs), so slots a tile never reached add nothing;
slot P is a bin that steps past the end of a list write into. On a GPU the kernels lower through
Triton; on a CPU they run in Pallas's interpret mode (exact, slow: for tests).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from cusgs_jax.splat.composite import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_STOP, Composite
from cusgs_jax.splat.tiles import TileGrid

DEFAULT_BATCH = 4  # Gaussians per unrolled step: their loads are issued together


def padded_channels(channels: int) -> int:
    """Cp: the next power of two ≥ C (Triton's blocks have power-of-two sides)."""
    return 1 << max(0, int(channels) - 1).bit_length()


def _check_tile_size(grid: TileGrid) -> None:
    ts = grid.tile_size
    if ts & (ts - 1):
        raise ValueError(f"the pallas compositor needs a power-of-two tile size (8 or 16), got {ts}")


def _compiler_params(grid: TileGrid, interpret: bool):
    if interpret:
        return None
    from jax.experimental.pallas import triton as pl_triton

    warps = max(1, min(8, grid.tile_size * grid.tile_size // 32))  # a thread per pixel of the tile
    params = getattr(pl_triton, "CompilerParams", None) or pl_triton.TritonCompilerParams  # its name before JAX 0.7
    return params(num_warps=warps, num_stages=1)


def _pixels(grid: TileGrid, tile, dtype):
    """Pixel centres and the inside mask of program ``tile``'s S pixels."""
    ts = grid.tile_size
    s = jnp.arange(ts * ts, dtype=jnp.int32)
    px = (tile % grid.tiles_x) * ts + s % ts
    py = (tile // grid.tiles_x) * ts + s // ts
    inside = (px < grid.width) & (py < grid.height)
    return px.astype(dtype) + 0.5, py.astype(dtype) + 0.5, inside


def _gaussian(slot, pairs_ref, field_refs, feat_ref, px, py):
    """Load the Gaussian in ``slot`` and evaluate it at the tile's pixels.

    Returns (fields (mx, my, a, b, c, o) scalars, feature [1, Cp], dx, dy, gauss, raw α, α) with
    [S] pixel vectors.
    """
    gid = pairs_ref[slot]
    mx, my, ca, cb, cc, op = (ref[gid] for ref in field_refs)
    feature = feat_ref[pl.ds(gid, 1), :]
    dx = mx - px
    dy = my - py
    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    gauss = jnp.exp(-jnp.maximum(sigma, 0.0))
    raw = op * gauss
    alpha = jnp.minimum(MAX_ALPHA, raw)
    ok = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    return (mx, my, ca, cb, cc, op), feature, dx, dy, gauss, raw, alpha, ok


def _forward_kernel(grid, batch, bin_slot, starts_ref, ends_ref, pairs_ref, mx_ref, my_ref, a_ref, b_ref, c_ref,
                    o_ref, feat_ref, _sig_zeros, _hit_zeros, color_ref, trans_ref, count_ref, last_ref, sig_ref,
                    hit_ref):
    tile = pl.program_id(0)
    dtype = color_ref.dtype
    px, py, inside = _pixels(grid, tile, dtype)
    start, end = starts_ref[tile], ends_ref[tile]
    fields = (mx_ref, my_ref, a_ref, b_ref, c_ref, o_ref)

    def cond(state):
        k, done = state[0], state[2]
        return (k < end) & (jnp.min(done) == 0)

    def body(state):
        k, trans, done, color, count, last = state
        for b in range(batch):
            slot = k + b
            live = slot < end
            (_, _, _, _, _, op), feature, _, _, _, _, alpha, ok = _gaussian(
                jnp.minimum(slot, end - 1), pairs_ref, fields, feat_ref, px, py)
            valid = ok & live & (done == 0)
            after = trans * (1.0 - alpha)
            stop = valid & (after <= TRANSMITTANCE_STOP)
            keep = valid & ~stop
            weight = jnp.where(keep, alpha * trans, 0.0)
            color = color + weight[:, None] * feature
            significance = jnp.sum(jnp.where(keep, op * trans, 0.0))
            hits = jnp.sum(keep.astype(jnp.int32))
            trans = jnp.where(keep, after, trans)
            done = jnp.where(stop, 1, done)
            count = count + keep.astype(jnp.int32)
            last = jnp.where(keep, slot - start + 1, last)
            target = jnp.where(live, slot, bin_slot)
            sig_ref[target] = significance
            hit_ref[target] = hits
        return k + batch, trans, done, color, count, last

    num_pixels = grid.tile_size * grid.tile_size
    init = (start, jnp.ones((num_pixels,), dtype), jnp.where(inside, 0, 1).astype(jnp.int32),
            jnp.zeros(color_ref.shape, dtype), jnp.zeros((num_pixels,), jnp.int32),
            jnp.zeros((num_pixels,), jnp.int32))
    _, trans, _, color, count, last = jax.lax.while_loop(cond, body, init)
    color_ref[...] = color
    trans_ref[...] = trans
    count_ref[...] = count
    last_ref[...] = last


def _backward_kernel(grid, batch, bin_slot, starts_ref, need_ref, pairs_ref, mx_ref, my_ref, a_ref, b_ref, c_ref,
                     o_ref, feat_ref, trans_ref, last_ref, g_color_ref, g_trans_ref, *refs):
    out_refs = refs[len(refs) // 2:]  # the first half are the aliased zero buffers
    g_field_refs, g_feat_ref = out_refs[:6], out_refs[6]
    tile = pl.program_id(0)
    dtype = trans_ref.dtype
    px, py, _ = _pixels(grid, tile, dtype)
    start = starts_ref[tile]
    fields = (mx_ref, my_ref, a_ref, b_ref, c_ref, o_ref)
    last = last_ref[...]
    g_color = g_color_ref[...]  # [S, Cp]
    trans_final = trans_ref[...]

    def body(step, state):
        trans, suffix = state
        top = start + need_ref[tile] - 1 - step * batch
        for b in range(batch):
            slot = top - b
            live = slot >= start
            (_, _, ca, cb, cc, _), feature, dx, dy, gauss, raw, alpha, ok = _gaussian(
                jnp.maximum(slot, start), pairs_ref, fields, feat_ref, px, py)
            kept = ok & live & (slot - start < last)
            a = jnp.where(kept, alpha, 0.0)
            one_minus = 1.0 - a
            before = trans / one_minus  # T_k from T_{k+1} (unchanged where not kept: a = 0)
            g_dot_c = jnp.sum(g_color * feature, axis=1)
            weight = a * before
            d_alpha = before * g_dot_c - suffix / one_minus
            d_alpha = jnp.where(kept & (raw < MAX_ALPHA), d_alpha, 0.0)
            d_sigma = -d_alpha * a
            sx = jnp.sum(d_sigma * dx)
            sy = jnp.sum(d_sigma * dy)
            grads = (ca * sx + cb * sy,  # ∂σ/∂μx = a dx + b dy
                     cc * sy + cb * sx,  # ∂σ/∂μy = c dy + b dx
                     0.5 * jnp.sum(d_sigma * dx * dx),
                     jnp.sum(d_sigma * dx * dy),
                     0.5 * jnp.sum(d_sigma * dy * dy),
                     jnp.sum(d_alpha * gauss))
            target = jnp.where(live, slot, bin_slot)
            for ref, value in zip(g_field_refs, grads):
                ref[target] = value
            g_feat_ref[pl.ds(target, 1), :] = jnp.sum(weight[:, None] * g_color, axis=0, keepdims=True)
            suffix = suffix + g_dot_c * weight
            trans = before
        return trans, suffix

    steps = (need_ref[tile] + batch - 1) // batch
    jax.lax.fori_loop(0, steps, body, (trans_final, trans_final * g_trans_ref[...]))


def _prepare(means2d, conics, opacities, features):
    channels = features.shape[1]
    cp = padded_channels(channels)
    feat = jnp.pad(features, ((0, 0), (0, cp - channels)))
    fields = (means2d[:, 0], means2d[:, 1], conics[:, 0], conics[:, 1], conics[:, 2], opacities)
    return fields, feat, cp


def _full():
    return pl.BlockSpec()


def _per_tile(grid: TileGrid, *trailing):
    num_pixels = grid.tile_size * grid.tile_size
    return pl.BlockSpec((None, num_pixels, *trailing), lambda t: (t, 0, *(0,) * len(trailing)))


def _forward(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, ends) -> Composite:
    _check_tile_size(grid)
    dtype = means2d.dtype
    num_gaussians, channels = features.shape
    fields, feat, cp = _prepare(means2d, conics, opacities, features)
    num_slots = pairs.shape[0]
    num_pixels = grid.tile_size * grid.tile_size
    zeros_sig, zeros_hit = jnp.zeros((num_slots + 1,), dtype), jnp.zeros((num_slots + 1,), jnp.int32)
    out_shape = (jax.ShapeDtypeStruct((grid.num_tiles, num_pixels, cp), dtype),
                 jax.ShapeDtypeStruct((grid.num_tiles, num_pixels), dtype),
                 jax.ShapeDtypeStruct((grid.num_tiles, num_pixels), jnp.int32),
                 jax.ShapeDtypeStruct((grid.num_tiles, num_pixels), jnp.int32),
                 jax.ShapeDtypeStruct(zeros_sig.shape, dtype),
                 jax.ShapeDtypeStruct(zeros_hit.shape, jnp.int32))
    inputs = (starts, ends, pairs, *fields, feat, zeros_sig, zeros_hit)
    color, trans, count, last, sig, hit = pl.pallas_call(
        partial(_forward_kernel, grid, batch, num_slots),
        out_shape=out_shape,
        grid=(grid.num_tiles,),
        in_specs=[_full() for _ in inputs],
        out_specs=(_per_tile(grid, cp), _per_tile(grid), _per_tile(grid), _per_tile(grid), _full(), _full()),
        input_output_aliases={len(inputs) - 2: 4, len(inputs) - 1: 5},
        interpret=interpret,
        compiler_params=_compiler_params(grid, interpret),
        name="composite_forward",
    )(*inputs)
    gid = jnp.clip(pairs, 0, num_gaussians - 1)  # slots past every list hold zeros
    significance = jnp.zeros((num_gaussians,), dtype).at[gid].add(sig[:num_slots])
    hits = jnp.zeros((num_gaussians,), jnp.int32).at[gid].add(hit[:num_slots])
    return Composite(color[..., :channels], trans, count, last, significance, hits)


def _backward(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, trans_final, last,
              g_color, g_trans):
    dtype = means2d.dtype
    num_gaussians, channels = features.shape
    fields, feat, cp = _prepare(means2d, conics, opacities, features)
    num_slots = pairs.shape[0]
    need = jnp.max(last, axis=-1).astype(jnp.int32)  # [T] slots each tile composited
    g_color = jnp.pad(g_color, ((0, 0), (0, 0), (0, cp - channels)))
    zeros = [jnp.zeros((num_slots + 1,), dtype) for _ in range(6)] + [jnp.zeros((num_slots + 1, cp), dtype)]
    inputs = (starts, need, pairs, *fields, feat, trans_final, last, g_color, g_trans, *zeros)
    first_zero = len(inputs) - len(zeros)
    outs = pl.pallas_call(
        partial(_backward_kernel, grid, batch, num_slots),
        out_shape=tuple(jax.ShapeDtypeStruct(z.shape, dtype) for z in zeros),
        grid=(grid.num_tiles,),
        in_specs=[*(_full() for _ in range(10)), _per_tile(grid), _per_tile(grid), _per_tile(grid, cp),
                  _per_tile(grid), *(_full() for _ in zeros)],
        out_specs=tuple(_full() for _ in zeros),
        input_output_aliases={first_zero + i: i for i in range(len(zeros))},
        interpret=interpret,
        compiler_params=_compiler_params(grid, interpret),
        name="composite_backward",
    )(*inputs)
    gid = jnp.clip(pairs, 0, num_gaussians - 1)
    per_slot = jnp.concatenate([jnp.stack([o[:num_slots] for o in outs[:6]], axis=-1),
                                outs[6][:num_slots, :channels]], axis=-1)
    grads = jnp.zeros((num_gaussians, 6 + channels), dtype).at[gid].add(per_slot)
    return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:]


@partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2))
def composite_tiles_pallas(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, ends):
    """:func:`~cusgs_jax.splat.composite.composite_tiles` as Pallas kernels (see the module doc).

    Args:
      grid: static :class:`TileGrid` (tile size a power of two).
      batch: static Gaussians per unrolled step of a tile's loop (B).
      interpret: static; True runs Pallas's interpreter (any backend; tests on the CPU), False
        lowers through Triton (NVIDIA GPUs).
      means2d: [G, 2], conics: [G, 3], opacities: [G], features: [G, C] in front-to-back order.
      pairs: [P] int32 sorted-Gaussian index per slot, grouped by tile.
      starts, ends: [T] int32 each tile's slot range.
    Returns:
      :class:`~cusgs_jax.splat.composite.Composite`; differentiable in ``colors`` and
      ``transmittance``.
    """
    return _forward(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, ends)


def _composite_fwd(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, ends):
    out = _forward(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, ends)
    return out, (means2d, conics, opacities, features, pairs, starts, out.transmittance, out.last)


def _composite_bwd(grid, batch, interpret, residuals, cotangents):
    means2d, conics, opacities, features, pairs, starts, trans_final, last = residuals
    grads = _backward(grid, batch, interpret, means2d, conics, opacities, features, pairs, starts, trans_final,
                      last, cotangents.colors, cotangents.transmittance)
    return (*grads, None, None, None)


composite_tiles_pallas.defvjp(_composite_fwd, _composite_bwd)
