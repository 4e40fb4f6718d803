"""Memory attention: per-pixel retrieval of a model's feature from its PSC bank.

For one foundation model with query slice ``q`` [c] (rendered per pixel) and PSC bank
bank [M, D] of entries ``m_s`` (see :mod:`cusgs_jax.memory.psc`)::

    k_s = normalize(P m_s)                  keys [M, c], P the key projection [c, D]
    a_s = softmax_s(cos(q, k_s) / T)        masked entries get weight exactly 0
    f~  = sum_s a_s m_s                     [D], the bank's original vectors
    f   = adapter(f~)                       [D]

Choices (docs/method.md#choice-of-score): the paper's ``q^T m_k / sqrt(d)`` mixes
dimensions (``q`` has c, ``m_k`` has D). Like M3 we project the bank into query space
and score by cosine similarity with a temperature; unlike M3's fixed random
projection, ``P`` is learnable (init N(0, 1/D)). Keys are computed once per step
(:func:`precompute_keys`), so per-pixel work is M x c. Cosine similarity makes the
score independent of the scale of queries, keys and ``P``; the temperature is
learnable as ``log_temperature`` (init ``log(0.05)``, M3's fixed value; freeze it
with an optimizer mask to reproduce M3). It is clipped to ``[-40, 40]`` in the
forward pass (T in about [4e-18, 2e17]) so ``1/T`` never overflows; its gradient is
zero outside that range. The adapter is cheap: per-channel affine (default) or
``I + U V^T`` low rank, plus a bias; a dense D x D adapter would dominate the model
size for LLaMA-sized features.

Numerics: everything is float32 by default and follows the inputs' dtype (float64
under ``jax.enable_x64`` for gradient checks). Normalisation is safe for zero and
huge vectors (zero in, zero out, finite gradient), the softmax subtracts the
(stop-gradient) maximum and masks with ``where`` on both sides of the ``exp``, so
all-masked rows give zero weights and extreme logits give no NaN in value or
gradient. Rows whose every bank entry is masked return exactly zero features (the
adapter bias is not added). Matmuls use ``Precision.HIGHEST`` unless told otherwise
(pass ``precision=jax.lax.Precision.DEFAULT`` to allow TF32 on GPU).

Shapes: ``...`` any batch shape (e.g. H, W), c query dim, M bank entries, D feature dim.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "LOG_TEMPERATURE_CLIP",
    "apply_adapter",
    "attend",
    "attention_weights",
    "cosines",
    "init_memory_head",
    "masked_softmax",
    "num_params",
    "precompute_keys",
    "safe_normalize",
    "scores",
]

LOG_TEMPERATURE_CLIP = 40.0
_HIGHEST = jax.lax.Precision.HIGHEST


def init_memory_head(key, query_dim: int, feature_dim: int, *, adapter: str = "affine", rank: int = 16,
                     temperature: float = 0.05, dtype=jnp.float32) -> dict:
    """Parameters of one model's memory head.

    Args:
      key: PRNG key.
      query_dim: c, this model's slice of the rendered query.
      feature_dim: D, the model's feature dimension.
      adapter: "affine" (f * scale + bias, scale [D] init 1, bias [D] init 0) or
        "lowrank" (f + (f V) U^T + bias, i.e. (I + U V^T) f, U [D, rank] ~ N(0, 1/D),
        V [D, rank] init 0 so the head starts as the identity; bias [D] init 0).
      rank: rank of the low-rank adapter.
      temperature: initial softmax temperature (stored as its log, learnable).
    Returns:
      {"key_proj": [c, D], "log_temperature": [], "adapter": {...}}. The adapter kind is
      encoded by its keys ("scale" vs "u"), so the dict is a plain pytree of arrays.
    """
    if query_dim < 1 or feature_dim < 1:
        raise ValueError(f"query_dim and feature_dim must be >= 1, got {query_dim}, {feature_dim}")
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    k_proj, k_u = jax.random.split(key)
    # inside a larger program XLA would merge the division into the draw's last multiplication (sqrt 2 · erfinv),
    # 1 ulp off what the draw and the division give one call at a time; the barrier keeps the draw whole
    def scaled_normal(k, shape):
        return jax.lax.optimization_barrier(jax.random.normal(k, shape, dtype)) / math.sqrt(feature_dim)

    params = {
        "key_proj": scaled_normal(k_proj, (query_dim, feature_dim)),
        "log_temperature": jnp.asarray(math.log(temperature), dtype),
    }
    if adapter == "affine":
        params["adapter"] = {"scale": jnp.ones((feature_dim,), dtype), "bias": jnp.zeros((feature_dim,), dtype)}
    elif adapter == "lowrank":
        if rank < 1:
            raise ValueError(f"rank must be >= 1, got {rank}")
        params["adapter"] = {
            "u": scaled_normal(k_u, (feature_dim, rank)),
            "v": jnp.zeros((feature_dim, rank), dtype),
            "bias": jnp.zeros((feature_dim,), dtype),
        }
    else:
        raise ValueError(f"adapter must be 'affine' or 'lowrank', got {adapter!r}")
    return params


def num_params(params: dict) -> int:
    """Total number of scalars in a memory head."""
    return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(params)))


def safe_normalize(x, axis: int = -1):
    """x / |x| along ``axis``; zero vectors map to zero with a finite (identity) gradient.

    The vector is first divided by its max-abs entry (a stop-gradient constant: the
    result is scale invariant, so the gradient is still exact), so the squared norm is
    in [1, n] for any non-zero input -- no overflow for huge or underflow for tiny
    vectors -- and the zero case is a ``where`` (a ``max`` would halve the gradient of
one-hot vectors, whose scaled squared norm is exactly 1). Shapes: x [..., n, ...].
    """
    x = jnp.asarray(x)
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axis, keepdims=True))
    scale = jnp.where(scale > 0, scale, jnp.ones_like(scale))
    y = x / scale
    sq = jnp.sum(y * y, axis=axis, keepdims=True)  # >= 1 unless x == 0
    return y * jax.lax.rsqrt(jnp.where(sq > 0, sq, jnp.ones_like(sq)))


def masked_softmax(logits, valid=None, axis: int = -1, *, scale=None):
    """Softmax of ``scale * logits`` along ``axis``, with masked entries at exactly zero.

    Computed as ``exp(scale * (logits - max))`` with the (stop-gradient) max over valid
    entries -- the shift is exact in value and gradient by shift invariance, the top
    entry is exactly ``exp(0) = 1``, and applying ``scale`` after the subtraction keeps a
    fused multiply-add from turning ``scale * logits - max`` into a huge positive
    rounding residue when ``scale * logits`` is ~1e17.

    Args:
      logits: [..., M] finite logits (any magnitude, e.g. +-1e30).
      valid: bool broadcastable to logits, or None (all valid).
      scale: optional positive scalar (e.g. 1 / temperature), differentiable; None = 1.
    Returns:
      [..., M] weights; a row with no valid entry is all zeros. Value and gradient are
      finite for finite inputs.
    """
    logits = jnp.asarray(logits)
    if valid is None:
        valid = jnp.ones(logits.shape, bool)
    valid = jnp.broadcast_to(jnp.asarray(valid, bool), logits.shape)
    neg_inf = jnp.asarray(-jnp.inf, logits.dtype)
    top = jnp.max(jnp.where(valid, logits, neg_inf), axis=axis, keepdims=True)
    top = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, jnp.zeros_like(top)))
    shifted = jnp.where(valid, logits - top, jnp.zeros_like(logits))  # <= 0 where valid
    if scale is not None:
        shifted = shifted * jnp.asarray(scale, logits.dtype)
    e = jnp.where(valid, jnp.exp(shifted), jnp.zeros_like(logits))
    total = jnp.sum(e, axis=axis, keepdims=True)  # >= 1 when any entry is valid
    return e / jnp.where(total > 0, total, jnp.ones_like(total))


def _inv_temperature(params):
    log_t = jnp.clip(params["log_temperature"], -LOG_TEMPERATURE_CLIP, LOG_TEMPERATURE_CLIP)
    return jnp.exp(-log_t)


def precompute_keys(params: dict, bank, *, precision=_HIGHEST):
    """Unit keys of the bank in query space.

    Args:
      params: memory head (uses "key_proj" [c, D]).
      bank: [M, D] PSC entries (original vectors).
    Returns:
      keys [M, c] = normalize(bank @ P^T) along c (zero rows give zero keys, score 0).
      Normalising the bank rows first would change nothing (positive scale).
    """
    proj = params["key_proj"]
    return safe_normalize(jnp.matmul(jnp.asarray(bank, proj.dtype), proj.T, precision=precision))


def cosines(queries, keys, *, precision=_HIGHEST):
    """cos(q, k_s): queries [..., c] (any scale; zero -> 0), keys [M, c] unit or zero -> [..., M]."""
    return jnp.matmul(safe_normalize(queries), jnp.asarray(keys).T, precision=precision)


def scores(params: dict, queries, keys, *, precision=_HIGHEST):
    """Attention logits cos(q, k_s) / T: queries [..., c], keys [M, c] -> [..., M]."""
    cos = cosines(queries, keys, precision=precision)
    return cos * _inv_temperature(params).astype(cos.dtype)


def attention_weights(params: dict, queries, keys, valid=None, *, precision=_HIGHEST):
    """Memory attention weights a = softmax over valid s of cos(q, k_s) / T.

    Args:
      queries: [..., c]; keys: [M, c]; valid: [M] bool (or broadcastable to [..., M]) or None.
    Returns:
      [..., M] weights summing to 1 over valid entries (zeros where masked / no valid entry).
    """
    cos = cosines(queries, keys, precision=precision)
    return masked_softmax(cos, valid, scale=_inv_temperature(params).astype(cos.dtype))


def apply_adapter(adapter: dict, features):
    """The output adapter on [..., D] features: affine (scale, bias) or low rank (u, v, bias)."""
    if "scale" in adapter:
        return features * adapter["scale"] + adapter["bias"]
    if "u" in adapter:
        low = jnp.matmul(jnp.matmul(features, adapter["v"], precision=_HIGHEST), adapter["u"].T,
                         precision=_HIGHEST)
        return features + low + adapter["bias"]
    raise ValueError(f"unknown adapter with keys {sorted(adapter)}")


def attend(params: dict, queries, keys, bank, valid=None, *, block: int | None = None,
           precision=_HIGHEST):
    """Retrieve features from the memory bank: adapter(softmax(cos(q, K) / T) @ bank).

    Args:
      params: memory head from :func:`init_memory_head`.
      queries: [..., c] rendered queries.
      keys: [M, c] from ``precompute_keys(params, bank)`` (recompute after each update of
        ``key_proj`` -- or inside the differentiated function to train ``key_proj``).
      bank: [M, D] PSC entries.
      valid: [M] bool mask of usable entries (e.g. a padded bank), or None.
      block: if set, process the flattened queries in blocks of ``block`` rows with
        ``lax.map`` and rematerialisation, so at most [block, M] weights exist at once
        (also in the backward pass). None: one pass over all queries.
      precision: matmul precision.
    Returns:
      [..., D] features; exactly zero for every row when no entry is valid.
    """
    queries = jnp.asarray(queries)
    keys = jnp.asarray(keys)
    bank = jnp.asarray(bank)
    if valid is not None:
        valid = jnp.asarray(valid, bool)
        if valid.shape != keys.shape[:1]:
            raise ValueError(f"valid must be [M] = {keys.shape[:1]}, got {valid.shape}")
    if keys.shape[0] != bank.shape[0]:
        raise ValueError(f"keys [M, c] and bank [M, D] disagree: {keys.shape} vs {bank.shape}")

    def run(q):
        a = attention_weights(params, q, keys, valid, precision=precision)
        f = apply_adapter(params["adapter"], jnp.matmul(a, bank.astype(a.dtype), precision=precision))
        if valid is not None:
            f = jnp.where(jnp.any(valid), f, jnp.zeros_like(f))
        return f

    if block is None:
        return run(queries)
    block = int(block)
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    batch, c = queries.shape[:-1], queries.shape[-1]
    flat = queries.reshape(-1, c)
    n = flat.shape[0]
    if n == 0:
        return run(queries)
    nblocks = -(-n // block)
    flat = jnp.pad(flat, ((0, nblocks * block - n), (0, 0)))
    out = jax.lax.map(jax.checkpoint(run), flat.reshape(nblocks, block, c))
    return out.reshape(nblocks * block, -1)[:n].reshape(batch + (out.shape[-1],))
