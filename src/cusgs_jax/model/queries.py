"""Hierarchical feature queries (CUS-GS, docs/method.md#hierarchical-queries).

Every anchor decodes a voxel query ``q_v = MLP_qv(z, d, e)`` and every Gaussian a
query ``q_{v,n} = Linear([q_v, Δx_{v,n}])``; the splatter composites them as extra
channels. The ablation ``per_gaussian`` instead learns one query per Gaussian
slot, stored with the anchors (``AnchorParams.query_table``).

Naming (:mod:`cusgs_jax.types`): S visible slots, N offsets, F latent,
E appearance, Q = Σ_m c_m query channels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cusgs_jax.config import FeatureConfig
from cusgs_jax.model.anchors import AnchorParams
from cusgs_jax.nn import apply_mlp, init_mlp


def init_query_heads(key, cfg: FeatureConfig, latent_dim: int, appearance_dim: int) -> dict:
    """Per-anchor query heads: {"voxel": MLP (F+3+E → hidden → Q), "gaussian": Linear (Q+3 → Q)}."""
    q = cfg.query_dim
    k1, k2 = jax.random.split(key)
    return {"voxel": init_mlp(k1, (latent_dim + 3 + appearance_dim, cfg.hidden, q)),
            "gaussian": init_mlp(k2, (q + 3, q))}


def decode_queries(heads: dict | None, anchor_params: AnchorParams, direction: jax.Array,
                   appearance: jax.Array | None) -> jax.Array:
    """Per-Gaussian queries of the decoded anchors.

    Args:
      heads: from :func:`init_query_heads`, or None for the per-Gaussian table.
      anchor_params: [S, …] gathered anchor arrays (latent, offsets; query_table
        when ``heads`` is None).
      direction: [S, 3] unit camera→anchor; appearance: [E] or None.
    Returns:
      [S·N, Q].
    """
    num, n = anchor_params.offsets.shape[:2]
    if heads is None:
        return anchor_params.query_table.reshape(num * n, -1)
    inputs = [anchor_params.latent, direction]
    if appearance is not None:
        inputs.append(jnp.broadcast_to(appearance, (num, appearance.shape[-1])))
    voxel = apply_mlp(heads["voxel"], jnp.concatenate(inputs, axis=-1))  # [S, Q]
    per_gaussian = jnp.concatenate([jnp.broadcast_to(voxel[:, None], (num, n, voxel.shape[-1])),
                                    anchor_params.offsets], -1)
    return apply_mlp(heads["gaussian"], per_gaussian).reshape(num * n, -1)
