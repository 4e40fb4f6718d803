"""The voxel-anchor scaffold (Scaffold-GS) and the one owner of every per-anchor array.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N Gaussians per anchor,
F latent size, Q query channels.

**Capacity.** Anchors live in arrays of a fixed capacity ``A``; ``alive`` says
which slots hold an anchor. Pruning clears bits and growing fills dead slots,
so the jitted step keeps its shapes. Only when every slot is taken does the
capacity grow (outside jit; the caller logs it and the step recompiles once).

**The capacity axis is declared by type.** Every array leaf under a node of a
:class:`PerAnchor` type has the anchor capacity as its leading axis:
:class:`AnchorState` (centres, alive, and its :class:`AnchorParams`), and the
densification statistics (:class:`cusgs_jax.densify.scaffold.GrowStats`,
:class:`cusgs_jax.densify.feature_prune.PruneStats`). Optax moments mirror the
parameter tree, so the ``AnchorParams`` node reappears inside them and is
found the same way. :func:`map_rows` is the one function that touches rows;
:func:`pad_rows`, :func:`take_rows` and :func:`zero_rows` grow, compact and
refill any pytree built of these types, and nothing else in the code knows
which leaves are per-anchor — a network weight whose width happens to equal
the capacity is never touched.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np


class PerAnchor:
    """Marker base: every array leaf of this node has the anchor capacity A as axis 0."""


def is_per_anchor(node) -> bool:
    return isinstance(node, PerAnchor)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AnchorParams(PerAnchor):
    """Learnable per-anchor arrays (the optimiser updates them; dead slots are masked).

    Attributes:
      offsets: [A, N, 3] offsets Δx in units of ``exp(log_scaling[:, :3])``.
      log_scaling: [A, 6] log scale: first 3 scale the offsets, last 3 are the
        base Gaussian scale.
      latent: [A, F] anchor feature z.
      query_table: [A, N, Q] a learned feature query per Gaussian slot
        (``model.query_granularity = "per_gaussian"``), else None.
    """

    offsets: jax.Array
    log_scaling: jax.Array
    latent: jax.Array
    query_table: Optional[jax.Array] = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AnchorState(PerAnchor):
    """Every per-anchor array, with an explicit capacity.

    Attributes:
      centers: [A, 3] voxel centres x_v (fixed, not optimised).
      alive: [A] bool, the slot holds an anchor.
      params: :class:`AnchorParams`, the learnable per-anchor arrays.
    """

    centers: jax.Array
    alive: jax.Array
    params: AnchorParams

    @property
    def capacity(self) -> int:
        return self.centers.shape[0]

    def replace(self, **changes) -> AnchorState:
        return dataclasses.replace(self, **changes)


# --- rows of any pytree built of PerAnchor nodes ------------------------------------------------


def map_rows(fn: Callable, tree):
    """Apply ``fn(x) -> x'`` to every array leaf under a :class:`PerAnchor` node of ``tree``.

    Other leaves (network weights, step counters, optax ``MaskedNode``s) are
    returned unchanged, whatever their shape.
    """
    def visit(node):
        if is_per_anchor(node):
            return jax.tree_util.tree_map(fn, node)
        return node

    return jax.tree_util.tree_map(visit, tree, is_leaf=is_per_anchor)


def pad_leaf(x, new_capacity: int) -> jax.Array:
    """[A, ...] → [new_capacity, ...], the new rows zero (False for bool)."""
    widths = [(0, new_capacity - x.shape[0])] + [(0, 0)] * (x.ndim - 1)
    return jnp.pad(jnp.asarray(x), widths)


def zero_leaf(x, rows) -> jax.Array:
    """[A, ...] with the rows where ``rows`` [A] bool is set replaced by zeros."""
    rows = jnp.asarray(rows)
    return jnp.where(rows.reshape((-1,) + (1,) * (x.ndim - 1)), jnp.zeros_like(x), x)


def pad_rows(tree, new_capacity: int):
    """Grow every per-anchor array to ``new_capacity`` rows; the new rows are zero (``alive`` False)."""
    return map_rows(lambda x: pad_leaf(x, new_capacity), tree)


def take_rows(tree, index):
    """Gather rows ``index`` [A'] of every per-anchor array (capacity becomes A')."""
    index = jnp.asarray(index)
    return map_rows(lambda x: jnp.asarray(x)[index], tree)


def zero_rows(tree, rows):
    """Zero the rows ``rows`` [A] bool of every per-anchor array (``alive`` → False)."""
    return map_rows(lambda x: zero_leaf(x, rows), tree)


# --- construction, refill, compaction -----------------------------------------------------------


def voxelize(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Unique voxel centres of points (Scaffold-GS ``voxelize_sample``).

    Args:
      points: [P, 3].
    Returns:
      [A0, 3] float32 ``round(p / l) · l`` deduplicated, in lexicographic order.
    """
    if points.shape[0] == 0:
        raise ValueError("cannot build anchors from an empty point cloud")
    cells = np.unique(np.round(np.asarray(points, np.float64) / voxel_size).astype(np.int64), axis=0)
    return (cells * voxel_size).astype(np.float32)


def nearest_neighbour_sq_dist(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean squared distance to the ``k`` nearest other points (3DGS ``distCUDA2``), by k-d tree.

    Args:
      points: [A0, 3].
    Returns:
      [A0] float64, clamped below at 1e-7 (1.0 for a single point).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    if len(pts) < 2:
        return np.ones(len(pts))
    k_eff = min(k, len(pts) - 1)
    dist, _ = cKDTree(pts).query(pts, k=k_eff + 1)  # column 0 is the point itself
    return np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), 1e-7)


def auto_voxel_size(points: np.ndarray) -> float:
    """``model.voxel_size=auto``: the median distance from an SfM point to its nearest neighbour.

    Scaffold-GS (``voxel_size <= 0``) takes the median of ``distCUDA2`` — a mean
    *squared* distance to 3 neighbours — as a length, which does not scale with
    the scene; we take a length (the nearest-neighbour spacing), so the rule is
    invariant to the scale of the model. Duplicate points are ignored.

    Args:
      points: [P, 3].
    """
    from scipy.spatial import cKDTree

    pts = np.unique(np.asarray(points, np.float64), axis=0)
    if len(pts) < 2:
        from cusgs_jax.errors import UserError

        raise UserError(f"model.voxel_size=auto: the scene's {len(points)} initial points lie at {len(pts)} distinct "
                        "location(s), which gives no spacing to size a voxel by: check the reconstruction's points "
                        "(points3D), or set model.voxel_size to a cell size (in units of the scene extent)")
    dist, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(dist[:, 1]))


def fresh_queries(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """[..., N, Q] per-Gaussian queries as a new anchor gets them: N(0, 0.1²)."""
    return 0.1 * jax.random.normal(key, shape)


def anchor_layout(points: np.ndarray, voxel_size: float, *, capacity: int | None = None,
                  capacity_factor: float = 2.0, ladder: bool = False) -> dict[str, np.ndarray]:
    """The host part of :func:`init_anchors` (NumPy): ``{"centers": [A, 3] float32, "log_scaling": [A, 6]
    float32, "alive": [A] bool}`` with the first A0 slots the voxelised points (the rest dead, at
    ``log(voxel_size)``); ``ladder``: the default capacity is :func:`capacity_rung` of ``capacity_factor`` · A0."""
    centers = voxelize(points, voxel_size)
    num = centers.shape[0]
    wanted = max(int(math.ceil(capacity_factor * num)), num)
    capacity = capacity or (capacity_rung(wanted) if ladder else wanted)
    if capacity < num:
        raise ValueError(f"capacity {capacity} is smaller than the {num} initial anchors")
    log_scale = np.log(np.sqrt(nearest_neighbour_sq_dist(centers)))
    pad = capacity - num
    full_centers = np.concatenate([centers, np.zeros((pad, 3), np.float32)]).astype(np.float32)
    log_scaling = np.concatenate([np.repeat(log_scale[:, None], 6, axis=1),
                                  np.full((pad, 6), math.log(voxel_size))]).astype(np.float32)
    alive = np.zeros(capacity, bool)
    alive[:num] = True
    return dict(centers=full_centers, log_scaling=log_scaling, alive=alive)


def anchors_of_layout(layout: dict, *, n_offsets: int, latent_dim: int, query_dim: int = 0,
                      key: jax.Array | None = None) -> AnchorState:
    """The :class:`AnchorState` of an :func:`anchor_layout` (traceable: the run builds it inside its one
    initialisation program): offsets and latents zero, a per-Gaussian query table drawn with ``key`` when
    Q = ``query_dim`` > 0."""
    capacity = layout["alive"].shape[0]
    table = None
    if query_dim > 0:
        table = fresh_queries(key if key is not None else jax.random.PRNGKey(0), (capacity, n_offsets, query_dim))
    params = AnchorParams(
        offsets=jnp.zeros((capacity, n_offsets, 3), jnp.float32),
        log_scaling=jnp.asarray(layout["log_scaling"]),
        latent=jnp.zeros((capacity, latent_dim), jnp.float32),
        query_table=table,
    )
    return AnchorState(jnp.asarray(layout["centers"]), jnp.asarray(layout["alive"]), params)


def init_anchors(points: np.ndarray, voxel_size: float, *, n_offsets: int = 10, latent_dim: int = 32,
                 capacity: int | None = None, capacity_factor: float = 2.0, ladder: bool = False,
                 query_dim: int = 0, key: jax.Array | None = None) -> AnchorState:
    """Anchors from an SfM point cloud (Scaffold-GS ``create_from_pcd``).

    Offsets and latents start at zero; ``log_scaling`` is ``log sqrt`` of the
    mean squared distance to the 3 nearest anchors, for all 6 entries.

    Args:
      points: [P, 3] SfM points.
      voxel_size: cell size l.
      capacity: total slots; default ``ceil(capacity_factor · A0)`` (with ``ladder``: its :func:`capacity_rung`).
      query_dim: Q > 0 adds a per-Gaussian query table drawn with ``key``.
    Returns:
      :class:`AnchorState` with the first A0 slots alive.
    """
    layout = anchor_layout(points, voxel_size, capacity=capacity, capacity_factor=capacity_factor, ladder=ladder)
    return anchors_of_layout(layout, n_offsets=n_offsets, latent_dim=latent_dim, query_dim=query_dim, key=key)


def place_anchors(anchors: AnchorState, slots: np.ndarray, centers: np.ndarray, latent: np.ndarray,
                  log_scale: np.ndarray, key: jax.Array) -> AnchorState:
    """New anchors in the (dead) slots ``slots`` (host side, between steps).

    Offsets start at 0, ``log_scaling`` at ``log_scale`` for all 6 entries and a
    per-Gaussian query table (when present) at fresh queries drawn with ``key``,
    so a refilled slot inherits nothing from the anchor that lived there.

    Args:
      slots: [K] int slot indices; centers: [K, 3]; latent: [K, F]; log_scale: [K].

    The new rows are laid out on the host as [A]-row arrays with a row mask and merged by one jitted
    program per capacity (:func:`_merge_rows`), so growing K anchors compiles nothing new for a new K.
    """
    slots = np.asarray(slots)
    rows = np.zeros(anchors.capacity, bool)
    rows[slots] = True
    full_centers = np.zeros((anchors.capacity, 3), np.float32)
    full_centers[slots] = centers
    full_latent = np.zeros((anchors.capacity, anchors.params.latent.shape[-1]), np.float32)
    full_latent[slots] = latent
    full_log = np.zeros(anchors.capacity, np.float32)
    full_log[slots] = log_scale
    return _merge_rows(anchors, rows, full_centers, full_latent, full_log, key)


@jax.jit
def _merge_rows(anchors: AnchorState, rows, centers, latent, log_scale, key) -> AnchorState:
    """:func:`place_anchors` on [A]-row arrays: rows [A] bool take the new values (traceable)."""
    params = anchors.params
    table = params.query_table
    if table is not None:
        table = jnp.where(rows[:, None, None], fresh_queries(key, table.shape), table)
    params = AnchorParams(offsets=jnp.where(rows[:, None, None], 0.0, params.offsets),
                          log_scaling=jnp.where(rows[:, None], log_scale[:, None], params.log_scaling),
                          latent=jnp.where(rows[:, None], latent, params.latent), query_table=table)
    return AnchorState(jnp.where(rows[:, None], centers, anchors.centers), anchors.alive | rows, params)


def capacity_rung(need: int, multiple: int = 64) -> int:
    """The anchor-capacity ladder: the smallest rung that holds ``need`` slots.

    Rungs are the multiples of ``max(multiple, 2^(⌊log₂ need⌋ − 2))``: four per doubling (2^k · 1, 1.25,
    1.5, 1.75), so a capacity pads at most 25 % once ``need`` ≥ 4 · ``multiple``. The compacted models of renders
    and exports stand on it, and with ``model.capacity_ladder`` every anchor capacity of a run — the first
    (``capacity_factor`` × the initial anchors), each growth and shrink — so runs whose counts fall on one rung
    (jobs of a voxel-size sweep) share programs through the persistent cache.
    """
    step = max(int(multiple), 2 ** max(int(need).bit_length() - 3, 0))
    return max(int(multiple), -(-int(need) // step) * step)


def compact(anchors: AnchorState, multiple: int = 64) -> AnchorState:
    """Drop dead slots so rendering pays only for alive anchors (host side, outside jit).

    Gathers the alive slots (in slot order) of every per-anchor array into a capacity of
    :func:`capacity_rung` (``alive`` rounded up to the capacity ladder: few distinct shapes, few
    compiles); the padding slots are dead. Decode the
    result with every slot visible (``visible_fraction = 1``), so no anchor is dropped.

    Returns:
      :class:`AnchorState` with capacity ``capacity_rung(alive, multiple)``.
    """
    keep = np.flatnonzero(np.asarray(anchors.alive))
    new_capacity = capacity_rung(len(keep), multiple)
    index = np.concatenate([keep, np.full(new_capacity - len(keep), keep[0] if len(keep) else 0)])
    compacted = take_rows(anchors, index)
    return compacted.replace(alive=jnp.asarray(np.arange(new_capacity) < len(keep)))


def parameter_counts(anchors: AnchorState) -> dict[str, int]:
    """Stored numbers of the alive anchors: {"anchors": centres + offsets + scaling + latent,
    "query_table": per-Gaussian queries (0 without a table)}."""
    alive = int(np.sum(np.asarray(anchors.alive)))
    per_row = lambda x: int(np.prod(x.shape[1:])) * alive  # noqa: E731
    params = anchors.params
    anchor_numbers = sum(per_row(x) for x in (params.offsets, params.log_scaling, params.latent))
    anchor_numbers += per_row(anchors.centers)  # centres are stored too, though not optimised
    table = 0 if params.query_table is None else per_row(params.query_table)
    return {"anchors": anchor_numbers, "query_table": table}
