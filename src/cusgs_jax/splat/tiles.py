"""Tile binning: tile–Gaussian intersections sorted by (tile, depth).

Shapes: G Gaussians, P = ``max_pairs`` intersection capacity, T tiles, R = row groups per
Gaussian (``min(tiles_y, ROW_GROUPS)``).

The pipeline sorts once per view and uses only static shapes:

1. Gaussians are sorted by camera depth (ties by index); culled ones last.
2. Each visible Gaussian owns a contiguous run of ``n_g`` pair slots, one per tile it
   reaches. With its conic and opacity, a tile is listed only where the Gaussian's α can reach
   the compositor's 1/255 at one of the tile's pixel centres (:func:`footprint_rows`: per tile
   row, the columns the opacity-aware ellipse spans in that row's band — Speedy-Splat's
   SnugBox and AccuTile); without them, every tile of the footprint box (gsplat
   ``isect_tiles``). Slots are handed out in depth order with a saturating prefix sum, so
   when the capacity is exceeded the *farthest* pairs are the ones dropped, and the number
   dropped is returned as ``overflow``.
3. One sort of the packed 32-bit key ``tile · G + depth rank`` orders the
   pairs by tile and front to back inside each tile.
4. ``tile_starts``/``tile_ends`` delimit every tile's run in the sorted list.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from cusgs_jax.scan import running_max, running_sum
from cusgs_jax.splat.project import ALPHA_THRESHOLD, _two_prod

ROW_GROUPS = 8
"""Most row groups a Gaussian's tiles are listed by: a Gaussian spanning more tile rows than this
(over 64 px at tile size 8) has its rows grouped (``ceil(rows / ROW_GROUPS)`` per group, each given
the columns its whole band needs), so the per-Gaussian tables stay [G, 8]. The demo's start model
spans at most 7 rows of 8 px: its pairs are the same with 8, 16 or 32 groups (0.03 % more with 4)."""

# Margins that make the ellipse test conservative against float32 rounding, both the
# compositor's (σ = ½(a dx² + c dy²) + b dx dy, α = o e^{−σ} ≥ 1/255) and this module's
# (docs/rasterizer.md#footprint-and-tiles). The compositor's σ exceeds the exact form of its
# rounded inputs by at most ~9u·(a dx² + c dy²)/2 + u·σ (u = 2⁻²⁴ ≈ 6e-8): the test uses the
# form with a and c shrunk by CONIC_SLACK ≈ 34u instead; its threshold ln(255 o) is raised by
# a relative and an absolute THRESHOLD_SLACK; its extents come from that ellipse scaled up by
# EXTENT_SLACK in σ (≫ the √u-sized error of a band's extent where it grazes the ellipse's top),
# and are widened by POSITION_SLACK relative to the pixel coordinates, plus 1e-3 px.
CONIC_SLACK = 2e-6
THRESHOLD_SLACK = 1e-5
EXTENT_SLACK = 1e-4
POSITION_SLACK = 1e-5


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


class FootprintRows(NamedTuple):
    """Which tiles each Gaussian is listed in: R row groups of consecutive tile rows, each with
    one run of columns.

    Group ``j`` of Gaussian ``g`` covers the tile rows ``row0 + j·step`` to
    ``min(row0 + (j + 1)·step, row1)`` (exclusive) and, in each of them, the columns
    ``col0[g, j]`` to ``col0[g, j] + cols[g, j]`` (exclusive): ``rows[g, j] · cols[g, j]`` tiles.

    Attributes:
      row0, row1: [G] int32 first and one past the last tile row listed.
      step: [G] int32 tile rows per group (≥ 1).
      col0: [G, R] int32 first column of each group.
      cols: [G, R] int32 columns per row of each group (0: none).
      ends: [G, R] int32 inclusive prefix sum over the groups of their tile counts, so
        ``ends[:, -1]`` is each Gaussian's number of tiles.
    """

    row0: jax.Array
    row1: jax.Array
    step: jax.Array
    col0: jax.Array
    cols: jax.Array
    ends: jax.Array


def _pixel_tiles(lo: jax.Array, hi: jax.Array, ts: int, size: int) -> tuple[jax.Array, jax.Array]:
    """Tiles ``first`` to ``last`` (inclusive) holding the pixel centres ``k + 0.5`` of the image's
    ``size`` pixels that lie in the coordinate range ``[lo, hi]``; ``last < first`` when none, and
    out-of-grid tiles (−1 or past the end) where the range leaves the image: callers clamp."""
    first = jnp.ceil(jnp.clip(lo, -1.0, size + 1.0) - 0.5)
    last = jnp.floor(jnp.clip(hi, -2.0, float(size)) - 0.5)
    first = jnp.floor(first / ts).astype(jnp.int32)
    last = jnp.floor(last / ts).astype(jnp.int32)
    return first, jnp.where(hi >= lo, last, first - 1)


def footprint_rows(means2d: jax.Array, radii: jax.Array, grid: TileGrid, conics: jax.Array | None = None,
                   opacities: jax.Array | None = None) -> FootprintRows:
    """The tiles each Gaussian is listed in.

    With ``conics`` and ``opacities`` (the compositor's), a tile is listed only when the
    opacity-aware ellipse ``½ dᵀ Q d ≤ ln(255 o)`` — where α = o e^{−σ} reaches the
    compositor's 1/255 — contains one of its pixel centres ``(j + 0.5, i + 0.5)``: the tile
    rows its y-extent reaches, and per row (group) the columns of the ellipse's x-extent over
    the row's band of pixel centres. The test is conservative against float32 rounding (module
    constants) and is intersected with the footprint box, so it only ever drops tiles of the
    box in which every pixel's α is below 1/255: the image is unchanged. Where the margins leave
    no ellipse (diagonal needles of standard deviation ≳ 550 px) the whole box is listed. Without ``conics``, every
    tile of the box (:func:`tile_bounds`) is listed.

    Args:
      means2d: [G, 2] pixel centres.
      radii: [G, 2] float footprint half-extents.
      grid: static tiling.
      conics: [G, 3] ``(a, b, c)`` with ``σ = ½(a dx² + c dy²) + b dx dy``, or None.
      opacities: [G] compositing opacities (with ``conics``).
    Returns:
      :class:`FootprintRows` (one group, the box, without ``conics``).
    """
    box = tile_bounds(means2d, radii, grid)
    x0, y0, x1, y1 = (box[:, i] for i in range(4))
    if conics is None:
        return FootprintRows(y0, y1, jnp.ones_like(y0), x0[:, None], (x1 - x0)[:, None],
                             ((x1 - x0) * (y1 - y0))[:, None])
    ts, dtype = grid.tile_size, means2d.dtype
    groups = min(grid.tiles_y, ROW_GROUPS)
    mx, my = means2d[:, 0], means2d[:, 1]
    qa = conics[:, 0] * (1.0 - CONIC_SLACK)
    qb = conics[:, 1]
    qc = conics[:, 2] * (1.0 - CONIC_SLACK)
    ac, ac_err = _two_prod(qa, qc)
    bb, bb_err = _two_prod(qb, qb)
    det = (ac - bb) + (ac_err - bb_err)  # a c − b², accurate for needles
    threshold = jnp.log(jnp.maximum(opacities, ALPHA_THRESHOLD) / ALPHA_THRESHOLD)
    threshold = threshold * (1.0 + THRESHOLD_SLACK) + THRESHOLD_SLACK
    level = 2.0 * threshold * (1.0 + EXTENT_SLACK)  # dᵀ Q d ≤ level
    ok = (det > 0) & (qa > 0) & (qc > 0) & jnp.isfinite(det) & jnp.isfinite(level)
    det_s = jnp.where(ok, det, 1.0)
    qa_s, qc_s = jnp.where(ok, qa, 1.0), jnp.where(ok, qc, 1.0)
    y_half = jnp.sqrt(level * qa_s / det_s)  # |dy| on the ellipse
    x_half = jnp.sqrt(level * qc_s / det_s)
    tip = -qb * jnp.sqrt(level / (qc_s * det_s))  # dy of the rightmost point (−tip: the leftmost)
    ok = ok & jnp.isfinite(y_half) & jnp.isfinite(x_half) & jnp.isfinite(tip)  # else: the box
    y_half, x_half, tip = (jnp.where(ok, v, 0.0) for v in (y_half, x_half, tip))
    y_slack = POSITION_SLACK * (jnp.abs(my) + y_half) + 1e-3
    x_slack = POSITION_SLACK * (jnp.abs(mx) + x_half) + 1e-3

    # Tile rows whose pixel centres the ellipse's y-extent reaches (SnugBox), inside the box.
    first, last = _pixel_tiles(my - y_half - y_slack, my + y_half + y_slack, ts, grid.height)
    row0 = jnp.where(ok, jnp.maximum(first, y0), y0)
    row1 = jnp.where(ok, jnp.minimum(last + 1, y1), y1)
    row1 = jnp.maximum(row1, row0)
    step = jnp.maximum(1, -(-(row1 - row0) // groups))

    # Per group: its band of pixel-centre rows, and the ellipse's x-extent over it (AccuTile).
    j = jnp.arange(groups, dtype=jnp.int32)
    g_row0 = row0[:, None] + j[None, :] * step[:, None]
    g_rows = jnp.clip(row1[:, None] - g_row0, 0, step[:, None])
    band_lo = (g_row0 * ts).astype(dtype) + 0.5 - my[:, None]
    band_hi = (jnp.minimum((g_row0 + g_rows) * ts, grid.height)).astype(dtype) - 0.5 - my[:, None]
    reach = (y_half + y_slack)[:, None]  # as for the rows (the band's edge may graze the top)
    lo = jnp.maximum(band_lo, -reach)
    hi = jnp.minimum(band_hi, reach)
    # The extremes in x: dy at the ellipse's right- and leftmost points, clamped into the band
    # (the right edge −b dy/a + w(dy) is concave in dy, the left one convex).
    tip = tip[:, None]
    centre = (-qb / qa_s)[:, None]
    width = (jnp.sqrt(det_s) / qa_s)[:, None]

    def edge(dy):
        near = jnp.maximum(y_half[:, None] - jnp.abs(dy), 0.0)
        return centre * dy, width * jnp.sqrt(near * (y_half[:, None] + jnp.abs(dy)))

    shift_r, w_r = edge(jnp.clip(tip, lo, jnp.maximum(hi, lo)))
    shift_l, w_l = edge(jnp.clip(-tip, lo, jnp.maximum(hi, lo)))
    x_lo = mx[:, None] + (shift_l - w_l) - x_slack[:, None]
    x_hi = mx[:, None] + (shift_r + w_r) + x_slack[:, None]
    x_hi = jnp.where(hi >= lo, x_hi, x_lo - 1.0)  # the band misses the ellipse
    c_first, c_last = _pixel_tiles(x_lo, x_hi, ts, grid.width)
    col0 = jnp.where(ok[:, None], jnp.maximum(c_first, x0[:, None]), x0[:, None])
    col1 = jnp.where(ok[:, None], jnp.minimum(c_last + 1, x1[:, None]), x1[:, None])
    cols = jnp.maximum(col1 - col0, 0)
    ends = running_sum((g_rows * cols).astype(jnp.int32), axis=1)
    return FootprintRows(row0, row1, step, col0, cols, ends)


def count_pairs(means2d: jax.Array, radii: jax.Array, visible: jax.Array, grid: TileGrid,
                conics: jax.Array | None = None, opacities: jax.Array | None = None) -> jax.Array:
    """[G] int32 tiles each Gaussian is binned into (0 when not ``visible``): the pairs
    :func:`intersect_tiles` gives it with the same arguments, before any capacity."""
    rows = footprint_rows(means2d, radii, grid, conics, opacities)
    return jnp.where(visible, rows.ends[:, -1], 0)


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


def _slot_pairs(rows: FootprintRows, starts: jax.Array, counts: jax.Array, max_pairs: int,
                grid: TileGrid) -> tuple[jax.Array, jax.Array]:
    """(owner [P], tile id [P]) of every slot: the Gaussian and the tile of its pair (slots past the
    pairs hold garbage: callers mask them).

    Each non-empty group ``k = g·R + j`` owns the slots ``starts[g] + ends[g, j − 1]`` onwards: its
    first slot is marked with ``k`` and a running max hands ``k`` to the rest; the slot's row and
    column then follow from its place in the group's rectangle.
    """
    num_gaussians, groups = rows.ends.shape
    before = jnp.concatenate([jnp.zeros((num_gaussians, 1), jnp.int32), rows.ends[:, :-1]], axis=1)
    first = starts[:, None] + before  # [G, R] first slot of each group
    live = (rows.ends > before) & (counts > 0)[:, None] & (first < max_pairs)
    first = jnp.where(live, first, max_pairs).reshape(-1)
    group_id = jnp.arange(num_gaussians * groups, dtype=jnp.int32)
    group = jnp.zeros(max_pairs, jnp.int32).at[first].max(group_id, mode="drop")
    group = running_max(group)
    owner, j = group // groups, group % groups
    per_group = jnp.stack([first, rows.col0.reshape(-1), rows.cols.reshape(-1)], axis=-1)[group]  # one gather
    per_owner = jnp.stack([rows.row0, rows.step], axis=-1)[owner]
    inner = jnp.arange(max_pairs, dtype=jnp.int32) - per_group[:, 0]
    cols = jnp.maximum(per_group[:, 2], 1)
    tile_y = per_owner[:, 0] + j * per_owner[:, 1] + inner // cols
    tile_x = per_group[:, 1] + inner % cols
    return owner, tile_y * grid.tiles_x + tile_x


def intersect_tiles(
    means2d: jax.Array,
    radii: jax.Array,
    depths: jax.Array,
    visible: jax.Array,
    grid: TileGrid,
    max_pairs: int,
    conics: jax.Array | None = None,
    opacities: jax.Array | None = None,
) -> TileIntersections:
    """Bin Gaussians into tiles with a fixed pair capacity.

    Args:
      means2d: [G, 2] pixel centres.
      radii: [G, 2] float footprint half-extents.
      depths: [G] camera z (sort key).
      visible: [G] bool; invisible Gaussians produce no pairs.
      grid: static tiling.
      max_pairs: static capacity P of tile–Gaussian pairs.
      conics, opacities: [G, 3] and [G], the compositor's; given, a Gaussian is listed only in
        the tiles where its α can reach 1/255 (:func:`footprint_rows`), None: in every tile of
        its footprint box (gsplat's binning; the same image, more pairs).
    Returns:
      :class:`TileIntersections`.
    """
    num_gaussians = means2d.shape[0]
    means2d, radii, depths = jax.lax.stop_gradient((means2d, radii, depths))
    index = jnp.arange(num_gaussians, dtype=jnp.int32)
    key = jnp.where(visible, depths, jnp.inf)
    _, order = jax.lax.sort((key, index), num_keys=1, is_stable=True)

    if conics is not None:
        conics, opacities = jax.lax.stop_gradient((conics[order], opacities[order]))
    rows = footprint_rows(means2d[order], radii[order], grid, conics, opacities)
    counts = jnp.where(visible[order], rows.ends[:, -1], 0)
    counts = jnp.minimum(counts, max_pairs)
    ends = _saturating_cumsum(counts, max_pairs)
    starts = jnp.concatenate([jnp.zeros(1, ends.dtype), ends[:-1]])  # exact where < max_pairs
    kept = jnp.clip(max_pairs - starts, 0, counts)
    overflow = jnp.sum(counts - kept)
    num_pairs = ends[-1] if num_gaussians else jnp.int32(0)

    owner, tile_id = _slot_pairs(rows, starts, counts, max_pairs, grid)
    tile_id = jnp.where(jnp.arange(max_pairs) < num_pairs, tile_id, grid.num_tiles)

    sorted_tiles, pair_gaussians = _sort_by_tile(
        tile_id, owner, grid.num_tiles, num_gaussians
    )
    tiles = jnp.arange(grid.num_tiles, dtype=jnp.int32)
    tile_starts = jnp.searchsorted(sorted_tiles, tiles, side="left").astype(jnp.int32)
    tile_ends = jnp.searchsorted(sorted_tiles, tiles, side="right").astype(jnp.int32)
    return TileIntersections(order, pair_gaussians, tile_starts, tile_ends, num_pairs, overflow)
