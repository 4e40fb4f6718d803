"""Scaffold-GS anchor growing and opacity-based pruning (DESIGN.md §1).

Statistics are accumulated inside the jitted step (:func:`accumulate_stats`);
growing and pruning run between steps on the host (:func:`adjust_anchors`),
writing new anchors into dead slots and clearing ``alive`` bits, so shapes
never change. Only when no dead slot is left does the capacity grow (the
caller logs it; that step recompiles once).

Naming: A anchor capacity, N offsets per anchor.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.optim import reset_rows
from cusgs_jax.scaffold import AnchorParams, Anchors, grow_capacity


@dataclasses.dataclass(frozen=True)
class GrowConfig:
    """Scaffold-GS densification schedule and thresholds (its defaults for 30k steps)."""

    stats_start: int = 500  # accumulate statistics from this step
    start: int = 1500  # first growing/pruning step
    stop: int = 15000  # last growing/pruning step
    interval: int = 100
    grad_threshold: float = 0.0002
    min_opacity: float = 0.005
    success_threshold: float = 0.8
    levels: int = 3  # update_depth
    init_factor: int = 16  # update_init_factor
    hierarchy_factor: int = 4  # update_hierachy_factor
    capacity_growth: float = 1.5


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GrowStats:
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
    def zeros(capacity: int, n_offsets: int) -> "GrowStats":
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


def adjust_anchors(anchor_params: AnchorParams, anchors: Anchors, stats: GrowStats, opt_state, cfg: GrowConfig,
                   voxel_size: float, rng: np.random.Generator):
    """Grow at ``cfg.levels`` levels, then prune weak anchors (Scaffold-GS ``adjust_anchor``).

    Runs on the host between jitted steps.

    Returns:
      (anchor_params, anchors, stats, opt_state, info) where info has
      ``grown``, ``pruned``, ``capacity`` and ``capacity_grew`` (old capacity
      or None).
    """
    capacity, n = anchor_params.offsets.shape[:2]
    centers = np.asarray(anchors.centers)
    alive = np.asarray(anchors.alive).copy()
    offsets = np.asarray(anchor_params.offsets)
    log_scaling = np.asarray(anchor_params.log_scaling)
    latent = np.asarray(anchor_params.latent)
    grad_accum = np.array(stats.grad_accum).reshape(-1)
    grad_count = np.array(stats.grad_count).reshape(-1)
    opacity_accum = np.asarray(stats.opacity_accum).copy()
    visits = np.asarray(stats.visits).copy()

    grads = np.where(grad_count > 0, grad_accum / np.maximum(grad_count, 1), 0.0)
    offset_mask = grad_count > cfg.interval * cfg.success_threshold * 0.5
    gaussian_alive = np.repeat(alive, n)
    all_xyz = (centers[:, None, :] + offsets * np.exp(log_scaling[:, None, :3])).reshape(-1, 3)
    parent_latent = np.repeat(latent, n, axis=0)

    new_centers, new_latents, new_cells = [], [], []
    grow_centers, grow_alive = centers.copy(), alive.copy()
    for level in range(cfg.levels):
        threshold = cfg.grad_threshold * (cfg.hierarchy_factor // 2) ** level
        candidates = (grads >= threshold) & offset_mask & gaussian_alive
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

    # the Gaussians that took part are reset (Scaffold-GS resets offset_denom/accum there)
    grad_accum[offset_mask] = 0.0
    grad_count[offset_mask] = 0.0

    old_capacity = None
    num_new = int(sum(len(c) for c in new_centers))
    free = np.nonzero(~alive)[0]
    anchor_params = AnchorParams(jnp.asarray(offsets), jnp.asarray(log_scaling), jnp.asarray(latent))
    stats = GrowStats(jnp.asarray(grad_accum.reshape(capacity, n)), jnp.asarray(grad_count.reshape(capacity, n)),
                      jnp.asarray(opacity_accum), jnp.asarray(visits))
    if num_new > len(free):
        old_capacity = capacity
        new_capacity = int(max(np.ceil(capacity * cfg.capacity_growth), alive.sum() + num_new))
        anchor_params, anchors, stats, opt_state = grow_capacity(
            (anchor_params, anchors, stats, opt_state), capacity, new_capacity)
        capacity = new_capacity
        alive = np.concatenate([alive, np.zeros(new_capacity - len(alive), bool)])
        free = np.nonzero(~alive)[0]
    centers = np.array(anchors.centers)
    offsets, log_scaling, latent = (np.array(x) for x in (anchor_params.offsets, anchor_params.log_scaling,
                                                          anchor_params.latent))
    grad_accum, grad_count, opacity_accum, visits = (np.array(x) for x in (
        stats.grad_accum, stats.grad_count, stats.opacity_accum, stats.visits))
    fresh = np.zeros(capacity, bool)
    if num_new:
        slots = free[:num_new]
        centers[slots] = np.concatenate(new_centers)
        latent[slots] = np.concatenate(new_latents)
        offsets[slots] = 0.0
        log_scaling[slots] = np.log(np.concatenate(new_cells))[:, None]
        alive[slots] = True
        fresh[slots] = True
        grad_accum[slots] = grad_count[slots] = 0.0
        opacity_accum[slots] = visits[slots] = 0.0

    # prune anchors seen often enough whose average opacity stayed tiny
    seasoned = visits > cfg.interval * cfg.success_threshold
    prune = alive & seasoned & (opacity_accum < cfg.min_opacity * visits)
    opacity_accum[seasoned] = 0.0
    visits[seasoned] = 0.0
    alive[prune] = False
    grad_accum[prune] = grad_count[prune] = 0.0

    anchor_params = AnchorParams(jnp.asarray(offsets), jnp.asarray(log_scaling), jnp.asarray(latent))
    anchors = Anchors(jnp.asarray(centers), jnp.asarray(alive))
    stats = GrowStats(jnp.asarray(grad_accum), jnp.asarray(grad_count), jnp.asarray(opacity_accum),
                      jnp.asarray(visits))
    opt_state = reset_rows(opt_state, jnp.asarray(fresh), capacity)
    info = dict(grown=num_new, pruned=int(prune.sum()), capacity=capacity, capacity_grew=old_capacity,
                alive=int(alive.sum()))
    return anchor_params, anchors, stats, opt_state, info
