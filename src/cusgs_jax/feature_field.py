"""Multimodal feature field: hierarchical queries, memory attention and the feature loss.

CUS-GS (DESIGN.md §1): every anchor decodes a voxel query ``q_v = MLP_qv(z, d, e)``
and every Gaussian a query ``q_{v,n} = Linear([q_v, Δx_{v,n}])``; the queries are
alpha-composited as extra channels by the splatter; model ``m`` reads its slice
of the rendered query and retrieves its feature from its PSC memory bank with
:func:`cusgs_jax.memory.attention.attend`.

Naming: A anchors, N offsets, F latent, E appearance, Q = Σ_m c_m query
channels, P sampled pixels, S memory entries, D feature dimension.

Nothing here is traced when a scene has no feature models: callers check
``FeatureConfig.enabled`` (a static Python bool) before calling in.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cusgs_jax.decode import apply_mlp, init_mlp
from cusgs_jax.memory.attention import attend, init_memory_head, precompute_keys


# M3's split of its 160 query channels when all six models are present.
M3_QUERY_DIMS = {"clip": 16, "siglip": 32, "dinov2": 32, "seem": 16, "llama3": 32, "llamav": 32}


@dataclasses.dataclass(frozen=True)
class FeatureModelConfig:
    """One foundation model's slice of the field (``query_dim`` 0 = M3's split, else 16)."""

    name: str
    query_dim: int = 0
    gamma: float = 0.8  # PSC cosine threshold
    adapter: str = "affine"


@dataclasses.dataclass(frozen=True)
class FeatureConfig:
    """Static feature-field configuration (closed over, never traced)."""

    models: tuple[FeatureModelConfig, ...] = ()
    hidden: int = 32
    granularity: str = "per_anchor"  # "per_anchor" (hierarchical) or "per_gaussian"
    weight: float = 0.5  # λ_e (M3)
    sample_pixels: int = 2000  # pixels per step for the feature loss; 0 = all
    max_bank_entries: int = 1024  # PSC cap per model (rows are scanned in a seeded random order)
    psc_rows: int = 200_000  # training pixels (seeded random subset) the PSC scan looks at
    auto_extract: bool = True  # extract missing built-in features (daisy, hog, gabor, semantic)

    def __post_init__(self):
        models = tuple(m if m.query_dim > 0 else dataclasses.replace(m, query_dim=M3_QUERY_DIMS.get(m.name, 16))
                       for m in self.models)
        object.__setattr__(self, "models", models)

    @property
    def enabled(self) -> bool:
        return bool(self.models)

    @property
    def query_dim(self) -> int:
        return sum(m.query_dim for m in self.models)

    def slices(self) -> list[tuple[str, slice]]:
        """(model name, channel slice of the query) in order."""
        out, start = [], 0
        for m in self.models:
            out.append((m.name, slice(start, start + m.query_dim)))
            start += m.query_dim
        return out


def init_query_heads(key, cfg: FeatureConfig, latent_dim: int, appearance_dim: int, n_offsets: int,
                     capacity: int) -> dict:
    """Query parameters.

    ``per_anchor``: {"voxel": MLP (F+3+E → hidden → Q), "gaussian": Linear (Q+3 → Q)}.
    ``per_gaussian`` (ablation): {"table": [A, N, Q]} a learned query per Gaussian slot.
    """
    q = cfg.query_dim
    if cfg.granularity == "per_gaussian":
        return {"table": 0.1 * jax.random.normal(key, (capacity, n_offsets, q))}
    if cfg.granularity != "per_anchor":
        raise ValueError(f"features.granularity must be per_anchor or per_gaussian, got {cfg.granularity!r}")
    k1, k2 = jax.random.split(key)
    return {"voxel": init_mlp(k1, (latent_dim + 3 + appearance_dim, cfg.hidden, q)),
            "gaussian": init_mlp(k2, (q + 3, q))}


def refill_query_table(table: jax.Array, rows: jax.Array, key) -> jax.Array:
    """Fresh queries (drawn as :func:`init_query_heads` draws them) for the slots ``rows``.

    A slot refilled by growing holds a new anchor; the per-Gaussian table
    (``per_gaussian`` granularity) must not hand it the queries learned for
    the anchor that lived there before.

    Args:
      table: [A, N, Q]; rows: [A] bool.
    Returns:
      [A, N, Q], unchanged where ``rows`` is False.
    """
    fresh = 0.1 * jax.random.normal(key, table.shape, table.dtype)
    return jnp.where(rows[:, None, None], fresh, table)


def decode_queries(params: dict, latent, direction, appearance, offsets, slots, cfg: FeatureConfig):
    """Per-Gaussian queries of the decoded anchors.

    Args:
      params: from :func:`init_query_heads`.
      latent: [V, F]; direction: [V, 3] unit camera→anchor; appearance: [E] or None;
      offsets: [V, N, 3] the anchors' learnable offsets Δx; slots: [V] anchor slots
        (used by the per-Gaussian table).
    Returns:
      [V·N, Q].
    """
    num, n = offsets.shape[:2]
    if cfg.granularity == "per_gaussian":
        return params["table"][slots].reshape(num * n, -1)
    inputs = [latent, direction]
    if appearance is not None:
        inputs.append(jnp.broadcast_to(appearance, (num, appearance.shape[-1])))
    voxel = apply_mlp(params["voxel"], jnp.concatenate(inputs, axis=-1))  # [V, Q]
    per_gaussian = jnp.concatenate([jnp.broadcast_to(voxel[:, None], (num, n, voxel.shape[-1])), offsets], -1)
    return apply_mlp(params["gaussian"], per_gaussian).reshape(num * n, -1)


def init_memory_heads(key, cfg: FeatureConfig, banks: dict) -> dict:
    """One attention head per model: {name: params}."""
    keys = jax.random.split(key, max(len(cfg.models), 1))
    return {m.name: init_memory_head(k, m.query_dim, banks[m.name].shape[1], adapter=m.adapter)
            for m, k in zip(cfg.models, keys)}


def retrieve(heads: dict, banks: dict, queries, cfg: FeatureConfig) -> dict:
    """Features of every model from rendered queries.

    Args:
      heads: {name: attention params}; banks: {name: [S_m, D_m]} PSC entries.
      queries: [..., Q] rendered query per pixel.
    Returns:
      {name: [..., D_m]}.
    """
    out = {}
    for name, sl in cfg.slices():
        keys = precompute_keys(heads[name], banks[name])  # once per call (per step)
        out[name] = attend(heads[name], queries[..., sl], keys, banks[name])
    return out


def feature_loss(predicted: jax.Array, target: jax.Array, valid: jax.Array) -> tuple[jax.Array, dict]:
    """M3's per-model loss: mean squared error + (1 − cosine) over valid pixels.

    Args:
      predicted, target: [P, D]; valid: [P] bool (all-zero targets are invalid).
    Returns:
      (loss, {"l2": …, "cos": …}).
    """
    w = valid.astype(predicted.dtype)
    count = jnp.maximum(jnp.sum(w), 1.0)
    l2 = jnp.sum(w * jnp.mean((predicted - target) ** 2, axis=-1)) / count
    eps = 1e-8
    cos = jnp.sum(predicted * target, -1) / jnp.maximum(
        jnp.linalg.norm(predicted, axis=-1) * jnp.linalg.norm(target, axis=-1), eps)
    cos_loss = jnp.sum(w * (1.0 - cos)) / count
    return l2 + cos_loss, {"l2": l2, "cos": cos_loss}
