"""Voxel-anchor scaffold (Scaffold-GS) with a fixed capacity and an alive mask.

Naming: A anchor capacity, N Gaussians (offsets) per anchor, F latent size.

Anchors live in arrays of a fixed capacity; ``alive`` says which slots hold an
anchor. Pruning clears bits, growing fills dead slots, and both keep shapes
static so the jitted train step never recompiles. Only when every slot is
taken does :func:`grow_capacity` reallocate (outside jit; the caller logs it).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AnchorParams:
    """Learnable per-anchor parameters.

    Attributes:
      offsets: [A, N, 3] offsets Δx in units of ``exp(log_scaling[:, :3])``.
      log_scaling: [A, 6] log scale: first 3 scale the offsets, last 3 are the
        base Gaussian scale.
      latent: [A, F] anchor feature z.
    """

    offsets: jax.Array
    log_scaling: jax.Array
    latent: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Anchors:
    """Fixed (not optimised) anchor state.

    Attributes:
      centers: [A, 3] voxel centres x_v (not optimised).
      alive: [A] bool, slot holds an anchor.
    """

    centers: jax.Array
    alive: jax.Array

    @property
    def capacity(self) -> int:
        return self.centers.shape[0]


def voxelize(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Unique voxel centres of points (Scaffold-GS ``voxelize_sample``).

    Args:
      points: [P, 3].
    Returns:
      [V, 3] float32 ``round(p / l) · l`` deduplicated, in lexicographic order.
    """
    if points.shape[0] == 0:
        raise ValueError("cannot build anchors from an empty point cloud")
    cells = np.unique(np.round(np.asarray(points, np.float64) / voxel_size).astype(np.int64), axis=0)
    return (cells * voxel_size).astype(np.float32)


def nearest_neighbour_sq_dist(points: np.ndarray, k: int = 3, block: int = 2048) -> np.ndarray:
    """Mean squared distance to the ``k`` nearest other points (3DGS ``distCUDA2``).

    Args:
      points: [V, 3].
    Returns:
      [V] float64, clamped below at 1e-7.
    """
    pts = np.asarray(points, np.float64)
    out = np.empty(len(pts))
    k_eff = min(k, max(len(pts) - 1, 1))
    for start in range(0, len(pts), block):
        chunk = pts[start:start + block]
        d2 = np.sum((chunk[:, None, :] - pts[None, :, :]) ** 2, axis=-1)
        d2[np.arange(len(chunk)), np.arange(start, start + len(chunk))] = np.inf
        if len(pts) == 1:
            out[start:start + len(chunk)] = 1.0
            continue
        out[start:start + len(chunk)] = np.mean(np.partition(d2, k_eff - 1, axis=1)[:, :k_eff], axis=1)
    return np.maximum(out, 1e-7)


def init_anchors(points: np.ndarray, voxel_size: float, *, n_offsets: int = 10, latent_dim: int = 32,
                 capacity: int | None = None, capacity_factor: float = 2.0) -> tuple[AnchorParams, Anchors]:
    """Anchors from an SfM point cloud (Scaffold-GS ``create_from_pcd``).

    Offsets and latents start at zero; ``log_scaling`` is ``log sqrt`` of the
    mean squared distance to the 3 nearest anchors, for all 6 entries.

    Args:
      points: [P, 3] SfM points.
      voxel_size: cell size l.
      capacity: total slots; default ``ceil(capacity_factor · V)``.
    Returns:
      (AnchorParams with [A, …] arrays, Anchors) with the first V slots alive.
    """
    centers = voxelize(points, voxel_size)
    num = centers.shape[0]
    capacity = capacity or max(int(math.ceil(capacity_factor * num)), num)
    if capacity < num:
        raise ValueError(f"capacity {capacity} is smaller than the {num} initial anchors")
    log_scale = np.log(np.sqrt(nearest_neighbour_sq_dist(centers)))
    pad = capacity - num
    full_centers = np.concatenate([centers, np.zeros((pad, 3), np.float32)])
    log_scaling = np.concatenate([np.repeat(log_scale[:, None], 6, axis=1),
                                  np.full((pad, 6), math.log(voxel_size))]).astype(np.float32)
    params = AnchorParams(
        offsets=jnp.zeros((capacity, n_offsets, 3), jnp.float32),
        log_scaling=jnp.asarray(log_scaling),
        latent=jnp.zeros((capacity, latent_dim), jnp.float32),
    )
    alive = np.zeros(capacity, bool)
    alive[:num] = True
    return params, Anchors(jnp.asarray(full_centers), jnp.asarray(alive))


def grow_capacity(tree, old_capacity: int, new_capacity: int):
    """Pad every array whose leading axis is ``old_capacity`` to ``new_capacity`` with zeros.

    Works on any pytree (params, optimiser state, statistics, anchors); the
    new slots are dead (``alive`` pads with False). Host-side, outside jit.
    """
    def pad(x):
        if isinstance(x, (jax.Array, np.ndarray)) and x.ndim >= 1 and x.shape[0] == old_capacity:
            widths = [(0, new_capacity - old_capacity)] + [(0, 0)] * (x.ndim - 1)
            return jnp.pad(x, widths)
        return x

    return jax.tree_util.tree_map(pad, tree)
