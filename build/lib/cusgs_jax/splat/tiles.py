"""Tile binning: tile–Gaussian intersections sorted by (tile, depth).

Shapes: G Gaussians, P = ``max_pairs`` intersection capacity, T tiles.

The pipeline sorts once per view and uses only static shapes:

1. Gaussians are sorted by camera depth (ties by index); culled ones last.
2. Each visible Gaussian owns a contiguous run of ``n_g`` pair slots, one per
   tile its footprint box touches (gsplat ``isect_tiles``). Slots are handed out
   in depth order with a saturating prefix sum, so when the capacity is
   exceeded the *farthest* pairs are the ones dropped, and the number dropped
   is returned as ``overflow``.
3. One sort of the packed 32-bit key ``tile · G + depth rank`` orders the
   pairs by tile and front to back inside each tile.
4. ``tile_starts``/``tile_ends`` delimit every tile's run in the sorted list.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class TileGrid(NamedTuple):
    """Static tiling of a ``height × width`` image into ``tile_size`` squares."""

    width: int
    height: int
    tile_size: int

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


class TileIntersections(NamedTuple):
    """Sorted tile–Gaussian pairs.

    Attributes:
      order: [G] int32 permutation sorting Gaussians front to back (culled last).
      pair_gaussians: [P] int32 index into the *depth-sorted* Gaussians, grouped
        by tile and front to back within a tile; unused slots hold 0.
      tile_starts: [T] int32 first slot of each tile.
      tile_ends: [T] int32 one past the last slot of each tile.
      num_pairs: [] int32 number of pairs kept.
      overflow: [] int32 number of pairs dropped because ``P`` was too small.
    """

    order: jax.Array
    pair_gaussians: jax.Array
    tile_starts: jax.Array
    tile_ends: jax.Array
    num_pairs: jax.Array
    overflow: jax.Array


def tile_bounds(means2d: jax.Array, radii: jax.Array, grid: TileGrid) -> jax.Array:
    """Tile box ``[x0, x1) × [y0, y1)`` touched by each footprint.

    Args:
      means2d: [G, 2] pixel centres.
      radii: [G, 2] footprint half-extents in pixels (float).
    Returns:
      [G, 4] int32 ``(x0, y0, x1, y1)`` clamped to the grid.
    """
    ts = float(grid.tile_size)
    lo = jnp.floor((means2d - radii) / ts)
    hi = jnp.ceil((means2d + radii) / ts)
    limit = jnp.array([grid.tiles_x, grid.tiles_y], dtype=means2d.dtype)
    lo = jnp.clip(lo, 0, limit).astype(jnp.int32)
    hi = jnp.clip(hi, 0, limit).astype(jnp.int32)
    return jnp.concatenate([lo, hi], axis=-1)


def _saturating_cumsum(counts: jax.Array, cap: int) -> jax.Array:
    """Inclusive prefix sum clipped at ``cap`` (never overflows int32)."""
    return jax.lax.associative_scan(lambda a, b: jnp.minimum(a + b, cap), counts)


def _sort_by_tile(tile_id: jax.Array, owner: jax.Array, num_tiles: int, num_gaussians: int):
    """Sort the slots by tile id, front to back inside a tile.

    ``owner`` is an index into the depth-sorted Gaussians, so ``(tile, owner)``
    is exactly the wanted order and unique (a Gaussian meets a tile once).
    When ``(num_tiles + 1) · G`` fits in int32 the pair is packed into one
    integer key: a single-array sort is ~5x faster on CPU than sorting a key
    with a payload. Otherwise it falls back to a stable key–payload sort.
    """
    if (num_tiles + 1) * max(num_gaussians, 1) < 2**31:
        packed = jnp.sort(tile_id * num_gaussians + owner)
        return packed // num_gaussians, packed % num_gaussians
    return jax.lax.sort((tile_id, owner), num_keys=1, is_stable=True)


def intersect_tiles(
    means2d: jax.Array,
    radii: jax.Array,
    depths: jax.Array,
    visible: jax.Array,
    grid: TileGrid,
    max_pairs: int,
) -> TileIntersections:
    """Bin Gaussians into tiles with a fixed pair capacity.

    Args:
      means2d: [G, 2] pixel centres.
      radii: [G, 2] float footprint half-extents.
      depths: [G] camera z (sort key).
      visible: [G] bool; invisible Gaussians produce no pairs.
      grid: static tiling.
      max_pairs: static capacity P of tile–Gaussian pairs.
    Returns:
      :class:`TileIntersections`.
    """
    num_gaussians = means2d.shape[0]
    means2d, radii, depths = jax.lax.stop_gradient((means2d, radii, depths))
    index = jnp.arange(num_gaussians, dtype=jnp.int32)
    key = jnp.where(visible, depths, jnp.inf)
    _, order = jax.lax.sort((key, index), num_keys=1, is_stable=True)

    box = tile_bounds(means2d[order], radii[order], grid)
    box_width = box[:, 2] - box[:, 0]
    counts = jnp.where(visible[order], box_width * (box[:, 3] - box[:, 1]), 0)
    counts = jnp.minimum(counts, max_pairs)
    ends = _saturating_cumsum(counts, max_pairs)
    starts = jnp.concatenate([jnp.zeros(1, ends.dtype), ends[:-1]])  # exact where < max_pairs
    kept = jnp.clip(max_pairs - starts, 0, counts)
    overflow = jnp.sum(counts - kept)
    num_pairs = ends[-1] if num_gaussians else jnp.int32(0)

    # Owner of each slot: mark each Gaussian's first slot, then running max.
    slot = jnp.arange(max_pairs, dtype=jnp.int32)
    first = jnp.where((counts > 0) & (starts < max_pairs), starts, max_pairs)
    owner = jnp.zeros(max_pairs, jnp.int32).at[first].max(index, mode="drop")
    owner = jax.lax.cummax(owner)
    local = slot - starts[owner]
    width_o = jnp.maximum(box_width[owner], 1)
    tile_x = box[owner, 0] + local % width_o
    tile_y = box[owner, 1] + local // width_o
    tile_id = jnp.where(slot < num_pairs, tile_y * grid.tiles_x + tile_x, grid.num_tiles)

    sorted_tiles, pair_gaussians = _sort_by_tile(
        tile_id, owner, grid.num_tiles, num_gaussians
    )
    tiles = jnp.arange(grid.num_tiles, dtype=jnp.int32)
    tile_starts = jnp.searchsorted(sorted_tiles, tiles, side="left").astype(jnp.int32)
    tile_ends = jnp.searchsorted(sorted_tiles, tiles, side="right").astype(jnp.int32)
    return TileIntersections(order, pair_gaussians, tile_starts, tile_ends, num_pairs, overflow)
