"""Scaffold-GS anchor growing and opacity-based pruning, as a densification strategy (docs/method.md#growing-and-opacity-pruning).

Statistics are accumulated inside the jitted step (:func:`accumulate_stats`);
growing and pruning run between steps on the host
(:meth:`ScaffoldStrategy.update`), writing new anchors into dead slots and
clearing ``alive`` bits, so shapes never change. Only when no dead slot is
left does the capacity grow (:func:`cusgs_jax.densify.ops.grow_capacity`:
anchors, optimiser moments and every strategy's statistics together; logged,
the step recompiles once).

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets per anchor, F latent size.
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import GrowConfig
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import Strategy, UpdateInfo
from cusgs_jax.model.anchors import AnchorState, PerAnchor, capacity_rung, place_anchors

log = logging.getLogger("cusgs_jax")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GrowStats(PerAnchor):
    """Running statistics between adjustments.

    Attributes:
      grad_accum: [A, N] Σ ‖∂L/∂μ_2D‖ (in 3DGS's NDC-scaled units).
      grad_count: [A, N] times each Gaussian was visible.
      opacity_accum: [A] Σ over visits of Σ_n max(opacity, 0).
      visits: [A] times the anchor was in the view frustum.
    """

    grad_accum: jax.Array
    grad_count: jax.Array
    opacity_accum: jax.Array
    visits: jax.Array

    @staticmethod
    def zeros(capacity: int, n_offsets: int) -> GrowStats:
        return GrowStats(jnp.zeros((capacity, n_offsets)), jnp.zeros((capacity, n_offsets)),
                         jnp.zeros(capacity), jnp.zeros(capacity))


def accumulate_stats(stats: GrowStats, anchor_visible: jax.Array, opacities: jax.Array,
                     gaussian_visible: jax.Array, grad2d: jax.Array, width: int, height: int,
                     enabled: jax.Array) -> GrowStats:
    """Scaffold-GS ``training_statis`` for one view (pure, jittable).

    Args:
      anchor_visible: [A] bool, anchors decoded for this view.
      opacities: [A, N] decoded opacities (switched-off ones ≤ 0).
      gaussian_visible: [A, N] bool, opacity > 0 and rasterised (radii > 0).
      grad2d: [A, N, 2] ∂L/∂μ_2D in pixels.
      enabled: [] bool, inside the statistics window.
    """
    # 3DGS measures the screen-space gradient in NDC: d pixel / d ndc = size / 2.
    scaled = grad2d * jnp.array([width / 2.0, height / 2.0])
    norm = jnp.linalg.norm(scaled, axis=-1)
    on = enabled.astype(jnp.float32)
    vis = anchor_visible.astype(jnp.float32) * on
    seen = gaussian_visible.astype(jnp.float32) * on
    return GrowStats(
        grad_accum=stats.grad_accum + norm * seen,
        grad_count=stats.grad_count + seen,
        opacity_accum=stats.opacity_accum + jnp.sum(jnp.maximum(opacities, 0.0), axis=-1) * vis,
        visits=stats.visits + vis,
    )


def accumulate_rows(stats: GrowStats, slots: jax.Array, valid: jax.Array, opacities: jax.Array,
                    gaussian_visible: jax.Array, grad2d: jax.Array, width: int, height: int,
                    enabled: jax.Array) -> GrowStats:
    """:func:`accumulate_stats` for the S gathered slots of one view, added in place: O(S·N).

    The same sums as scattering every input to [A] and calling :func:`accumulate_stats`,
    without touching the rows the view did not see (one scatter-add of S rows per leaf
    instead of four [A]-sized scatters and dense adds).

    Args:
      slots: [S] int32 anchor slot of each gathered entry; valid: [S] bool (padding entries,
        which may repeat a slot, add nothing).
      opacities: [S, N]; gaussian_visible: [S, N] bool; grad2d: [S, N, 2] — gathered order.
    """
    capacity = stats.visits.shape[0]
    on = valid & jnp.asarray(enabled, bool)
    index = jnp.where(on, slots, capacity)  # out of range: dropped
    scaled = grad2d * jnp.array([width / 2.0, height / 2.0])
    seen = gaussian_visible & on[:, None]

    def add(acc, x):
        return acc.at[index].add(x, mode="drop")

    # jnp.where, not a product with 0: a non-finite gradient of a skipped step adds exactly 0
    return GrowStats(
        grad_accum=add(stats.grad_accum, jnp.where(seen, jnp.linalg.norm(scaled, axis=-1), 0.0)),
        grad_count=add(stats.grad_count, seen.astype(jnp.float32)),
        opacity_accum=add(stats.opacity_accum, jnp.where(on, jnp.sum(jnp.maximum(opacities, 0.0), axis=-1), 0.0)),
        visits=add(stats.visits, on.astype(jnp.float32)),
    )


def _grow_level(centers, alive, candidate_xyz, candidate_latent, cell):
    """New anchor centres and latents for one level (host NumPy).

    Candidates are snapped to cells of size ``cell``; cells already holding an
    alive anchor are skipped; a new anchor's latent is the element-wise max of
    its candidates' parent latents (Scaffold-GS uses ``scatter_max``).
    """
    if len(candidate_xyz) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, candidate_latent.shape[1]), np.float32)
    cand_cells = np.round(candidate_xyz / cell).astype(np.int64)
    unique, inverse = np.unique(cand_cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    occupied = {tuple(c) for c in np.round(centers[alive] / cell).astype(np.int64)}
    fresh = np.array([tuple(c) not in occupied for c in unique], bool)
    latent = np.full((len(unique), candidate_latent.shape[1]), -np.inf, np.float32)
    np.maximum.at(latent, inverse, candidate_latent)
    return (unique[fresh] * cell).astype(np.float32), latent[fresh]


def plan_growth(anchors: AnchorState, stats: GrowStats, cfg: GrowConfig, voxel_size: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scaffold-GS ``anchor_growing`` at ``cfg.levels`` levels (host NumPy).

    Returns:
      (centres [K, 3], latents [K, F], log cell sizes [K] of the new anchors,
      took_part [A, N] bool: the Gaussians whose gradient statistics are reset).
    """
    capacity, n = anchors.params.offsets.shape[:2]
    centers, alive = np.asarray(anchors.centers), np.asarray(anchors.alive)
    offsets, log_scaling = np.asarray(anchors.params.offsets), np.asarray(anchors.params.log_scaling)
    grad_accum, grad_count = np.asarray(stats.grad_accum).reshape(-1), np.asarray(stats.grad_count).reshape(-1)
    grads = np.where(grad_count > 0, grad_accum / np.maximum(grad_count, 1), 0.0)
    took_part = grad_count > cfg.interval * cfg.success_threshold * 0.5
    gaussian_alive = np.repeat(alive, n)
    all_xyz = (centers[:, None, :] + offsets * np.exp(log_scaling[:, None, :3])).reshape(-1, 3)
    parent_latent = np.repeat(np.asarray(anchors.params.latent), n, axis=0)

    new_centers, new_latents, new_cells = [], [], []
    grow_centers, grow_alive = centers.copy(), alive.copy()
    for level in range(cfg.levels):
        threshold = cfg.grad_threshold * (cfg.hierarchy_factor // 2) ** level
        candidates = (grads >= threshold) & took_part & gaussian_alive
        candidates &= rng.random(candidates.shape) > 0.5 ** (level + 1)
        cell = voxel_size * (cfg.init_factor // cfg.hierarchy_factor ** level)
        xyz, lat = _grow_level(grow_centers, grow_alive, all_xyz[candidates], parent_latent[candidates], cell)
        if len(xyz):
            new_centers.append(xyz)
            new_latents.append(lat)
            new_cells.append(np.full(len(xyz), cell, np.float32))
            # later levels also avoid cells taken by anchors grown at this level
            grow_centers = np.concatenate([grow_centers, xyz])
            grow_alive = np.concatenate([grow_alive, np.ones(len(xyz), bool)])
    if not new_centers:
        latent_dim = parent_latent.shape[1]
        return (np.zeros((0, 3), np.float32), np.zeros((0, latent_dim), np.float32), np.zeros(0, np.float32),
                took_part.reshape(capacity, n))
    return (np.concatenate(new_centers), np.concatenate(new_latents), np.log(np.concatenate(new_cells)),
            took_part.reshape(capacity, n))


def opacity_prune(alive: np.ndarray, stats: GrowStats, cfg: GrowConfig) -> tuple[np.ndarray, GrowStats]:
    """Scaffold-GS ``prune_anchor``: anchors seen often enough whose average opacity stayed tiny.

    Returns:
      (prune [A] bool, statistics with the seasoned anchors' opacity counters and
      the pruned anchors' gradient counters reset).
    """
    grad_accum, grad_count, opacity_accum, visits = (np.array(x) for x in (
        stats.grad_accum, stats.grad_count, stats.opacity_accum, stats.visits))
    seasoned = visits > cfg.interval * cfg.success_threshold
    prune = alive & seasoned & (opacity_accum < cfg.min_opacity * visits)
    opacity_accum[seasoned] = 0.0
    visits[seasoned] = 0.0
    grad_accum[prune] = grad_count[prune] = 0.0
    return prune, GrowStats(*(jax.device_put(x) for x in (grad_accum, grad_count, opacity_accum, visits)))


@jax.jit
def _reset_gradients(stats: GrowStats, took_part) -> GrowStats:
    """``stats`` with the gradient sums of the Gaussians ``took_part`` [A, N] bool zeroed (one program)."""
    return dataclasses.replace(stats, grad_accum=jnp.where(took_part, 0.0, stats.grad_accum),
                               grad_count=jnp.where(took_part, 0.0, stats.grad_count))


NEXT_CAPACITY_USE = 0.85  # alive share of the capacity from which its next growth is expected (next_capacity)


class ScaffoldStrategy(Strategy):
    """Scaffold-GS growing + opacity pruning (``adjust_anchor``) as a densification strategy.

    State: :class:`GrowStats`, accumulated in the jitted step (:meth:`accumulate`);
    :meth:`update` runs every ``grow.interval`` steps in ``[grow.start, grow.stop]``.
    """

    name = "scaffold"

    def __init__(self, cfg: GrowConfig, voxel_size: float, n_offsets: int, seed: int, ladder: bool = False):
        self.cfg, self.voxel_size, self.n_offsets, self.seed = cfg, voxel_size, n_offsets, seed
        self.ladder = ladder  # model.capacity_ladder: a grown capacity is a rung of model/anchors.py::capacity_rung

    def init_state(self, capacity: int) -> GrowStats:
        return GrowStats.zeros(capacity, self.n_offsets)

    def accumulate(self, stats: GrowStats, view) -> GrowStats:
        """Inside the step: one view's screen-space gradients, opacities and visits, added to its S slots."""
        n = self.n_offsets
        enabled = (view.step >= self.cfg.stats_start) & (view.step < self.cfg.stop) & view.finite
        visible = (view.gaussians.active & view.render.visible).reshape(-1, n)
        return accumulate_rows(stats, view.slots.slots, view.slots.valid, view.gaussians.opacities.reshape(-1, n),
                               visible, view.grad2d.reshape(-1, n, 2), view.width, view.height, enabled)

    def due(self, step: int) -> bool:
        """An adjustment after ``step`` completed steps."""
        return self.cfg.start <= step <= self.cfg.stop and step % self.cfg.interval == 0

    def next_capacity(self, state, step: int) -> int | None:
        """:meth:`grown_capacity` of A once the alive anchors fill :data:`NEXT_CAPACITY_USE` of A while
        growth is still scheduled: what :meth:`update` grows a full capacity to (unless one growth alone
        needs more)."""
        capacity = state.anchors.capacity
        if step >= self.cfg.stop or np.sum(np.asarray(state.anchors.alive)) < NEXT_CAPACITY_USE * capacity:
            return None
        return self.grown_capacity(capacity, 0)

    def grown_capacity(self, capacity: int, need: int) -> int:
        """The anchor capacity a full capacity of ``capacity`` slots grows to when ``need`` slots must be
        alive: the larger of ``ceil(A · grow.capacity_growth)`` and ``need`` — with the ladder, its rung
        (:func:`~cusgs_jax.model.anchors.capacity_rung`)."""
        grown = max(int(np.ceil(capacity * self.cfg.capacity_growth)), int(need))
        return capacity_rung(grown) if self.ladder else grown

    def generator(self, step: int) -> np.random.Generator:
        """The candidate-dropping draws of the adjustment after ``step`` steps (seeded: resumes replay it)."""
        return np.random.default_rng([self.seed, step - 1])

    def update(self, state, tx, step: int) -> tuple[object, UpdateInfo]:
        """Grow, then prune weak anchors (host side, after ``step`` completed steps).

        Returns:
          (state, :class:`~cusgs_jax.densify.base.UpdateInfo`): ``grown`` new anchors, ``pruned`` by
          opacity, ``capacity_changed`` when A grew; ``extra`` ``alive`` (anchors after the update)
          and ``capacity`` (A after it).
        """
        stats = state.densify[self.name]
        centers, latents, log_cells, took_part = plan_growth(state.anchors, stats, self.cfg, self.voxel_size,
                                                             self.generator(step))
        # the Gaussians that took part are reset (Scaffold-GS resets offset_denom/accum there)
        stats = _reset_gradients(stats, took_part)
        state = state.replace(densify={**state.densify, self.name: stats})
        capacity = old_capacity = state.anchors.capacity
        alive = np.asarray(state.anchors.alive)
        free = np.flatnonzero(~alive)
        if len(centers) > len(free):
            capacity = self.grown_capacity(capacity, alive.sum() + len(centers))
            state = ops.grow_capacity(state, tx, capacity)
            log.warning("anchor capacity full: grew %d -> %d slots (the step recompiles once)", old_capacity, capacity)
            free = np.flatnonzero(~np.asarray(state.anchors.alive))
        if len(centers):
            slots = free[:len(centers)]
            key = jax.random.fold_in(jax.random.PRNGKey(self.seed), step - 1)
            anchors = place_anchors(state.anchors, slots, centers, latents, log_cells, key)
            rows = np.zeros(capacity, bool)
            rows[slots] = True
            state = ops.restart_rows(state.replace(anchors=anchors), tx, rows)
        prune, stats = opacity_prune(np.asarray(state.anchors.alive), state.densify[self.name], self.cfg)
        anchors = state.anchors.replace(alive=jax.device_put(np.asarray(state.anchors.alive) & ~prune))
        state = state.replace(anchors=anchors, densify={**state.densify, self.name: stats})
        return state, UpdateInfo(grown=len(centers), pruned=int(prune.sum()), capacity_changed=capacity != old_capacity,
                                 extra=dict(alive=int(np.sum(np.asarray(anchors.alive))), capacity=capacity))
