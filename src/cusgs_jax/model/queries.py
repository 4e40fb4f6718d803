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
from cusgs_jax.model.decode import ViewInputs
from cusgs_jax.nn import apply_mlp, init_mlp
from cusgs_jax.precision import network_precision


def init_query_heads(key, cfg: FeatureConfig, latent_dim: int, appearance_dim: int) -> dict:
    """Per-anchor query heads: {"voxel": MLP (F+3+E → hidden → Q), "gaussian": Linear (Q+3 → Q)}."""
    q = cfg.query_dim
    k1, k2 = jax.random.split(key)
    return {"voxel": init_mlp(k1, (latent_dim + 3 + appearance_dim, cfg.hidden, q)),
            "gaussian": init_mlp(k2, (q + 3, q))}


def decode_queries(heads: dict | None, inputs: ViewInputs, precision: str = "highest") -> jax.Array:
    """Per-Gaussian queries of the view's anchors.

    Args:
      heads: from :func:`init_query_heads`, or None for the per-Gaussian table.
      inputs: the view's :class:`~cusgs_jax.model.decode.ViewInputs` [S] — the same latents,
        offsets, view directions d and appearance e the Gaussian heads decode (``rows.query_table``
        when ``heads`` is None).
      precision: the heads' matmul precision, a ``model.matmul_precision`` value (:mod:`cusgs_jax.precision`).
    Returns:
      [S·N, Q].
    """
    rows = inputs.rows
    num, n = rows.offsets.shape[:2]
    if heads is None:
        return rows.query_table.reshape(num * n, -1)
    parts = [rows.latent, inputs.direction]
    if inputs.appearance is not None:
        parts.append(jnp.broadcast_to(inputs.appearance, (num, inputs.appearance.shape[-1])))
    voxel = apply_mlp(heads["voxel"], jnp.concatenate(parts, axis=-1), network_precision(precision))  # [S, Q]
    per_gaussian = jnp.concatenate([jnp.broadcast_to(voxel[:, None], (num, n, voxel.shape[-1])),
                                    rows.offsets], -1)
    return apply_mlp(heads["gaussian"], per_gaussian, network_precision(precision)).reshape(num * n, -1)
