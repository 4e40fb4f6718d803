"""The feature field's read-out: memory attention per feature model, and M3's feature loss.

Model ``m`` reads its slice of the rendered query and retrieves its feature
from its PSC memory bank with :func:`cusgs_jax.memory.attention.attend`.
Naming (:mod:`cusgs_jax.types`): Q query channels, P sampled pixels,
M memory entries, D feature dimension, H×W image.

Nothing here is traced when a scene has no feature models: callers check
``FeatureConfig.enabled`` (a static Python bool) before calling in.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import FeatureConfig
from cusgs_jax.memory.attention import attend, init_memory_head, precompute_keys


def init_memory_heads(key, cfg: FeatureConfig, banks: dict) -> dict:
    """One attention head per model: {name: params}."""
    keys = jax.random.split(key, max(len(cfg.model_list), 1))
    return {m.name: init_memory_head(k, m.query_dim, banks[m.name].shape[1], adapter=m.adapter)
            for m, k in zip(cfg.model_list, keys)}


def retrieve(heads: dict, banks: dict, queries, cfg: FeatureConfig) -> dict:
    """Features of every model from rendered queries.

    Args:
      heads: {name: attention params}; banks: {name: [M, D]} PSC entries.
      queries: [..., Q] rendered query per pixel.
    Returns:
      {name: [..., D]}.
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


def stratified_pixels(key: jax.Array, total: int, count: int) -> jax.Array:
    """[count] int32 pixel indices in [0, ``total``): one drawn uniformly in each of ``count`` equal
    consecutive strata of the raster order (stratified sampling, O(count); ``jax.random.choice``
    without replacement would permute all ``total`` pixels, a sort of H·W keys per step).

    Exact in integers: stratum i is the range [i·total, (i+1)·total) of ``total·count`` sub-pixel
    units, a unit ``x`` lies in pixel ``x // count``, so every pixel is drawn with probability
    ``count / total`` exactly. Strata overlap only at a pixel their boundary cuts, so a pixel is
    drawn twice only in that rare case.
    """
    offset = jax.random.randint(key, (count,), 0, total, dtype=jnp.int32)
    units = jnp.arange(count, dtype=jnp.int32) * total + offset
    return units // count


def image_pixel_of(row, col, feature_hw: tuple[int, int], image_hw: tuple[int, int]) -> tuple[jax.Array, jax.Array]:
    """The image pixel a feature-map pixel reads: the one whose centre is nearest to its own.

    Args:
      row, col: [P] int feature-map pixel indices of an h×w map (``feature_hw`` = (h, w)).
      image_hw: (H, W) of the image.
    Returns:
      ([P] int32 image rows, [P] int32 image columns). What :func:`sampled_feature_loss` samples and
      what :func:`cusgs_jax.training.inputs.mask_feature_maps` masks by.
    """
    (fh, fw), (height, width) = feature_hw, image_hw
    img_row = jnp.minimum(((jnp.asarray(row) + 0.5) * height / fh).astype(jnp.int32), height - 1)
    img_col = jnp.minimum(((jnp.asarray(col) + 0.5) * width / fw).astype(jnp.int32), width - 1)
    return img_row, img_col


def read_pixels(feature_hw: dict, image_hw: tuple[int, int], max_fraction: float = 0.25) -> tuple[int, ...] | None:
    """The flat image pixels (``row · W + column``) :func:`sampled_feature_loss` can read: the pixel nearest
    each feature-map pixel's centre (:func:`image_pixel_of`), over every model — what the rendered queries are
    needed at (``splat.SparseChannels``). None when they cover more than ``max_fraction`` of the image: a map
    finer than stride 2, where a tile lists more than 16 of its 64 pixels and compositing there only is no
    longer cheaper (``benchmarks/sparse_channels.py``).

    Args:
      feature_hw: {name: (h, w)} each model's feature-map size (static shapes).
      image_hw: (H, W).
    """
    height, width = image_hw
    flat = []
    with jax.ensure_compile_time_eval():  # the very arithmetic the loss traces, on concrete indices
        for fh, fw in feature_hw.values():
            index = np.arange(fh * fw)
            row, col = image_pixel_of(index // fw, index % fw, (fh, fw), (height, width))
            flat.append(np.asarray(row, np.int64) * width + np.asarray(col, np.int64))
    pixels = np.unique(np.concatenate(flat)) if flat else np.zeros(0, np.int64)
    if pixels.size == 0 or pixels.size > max_fraction * height * width:
        return None
    return tuple(int(p) for p in pixels)


def sampled_feature_loss(queries: jax.Array, targets: dict, heads: dict, banks: dict, key: jax.Array,
                         cfg: FeatureConfig) -> tuple[jax.Array, dict]:
    """Σ over models of :func:`feature_loss` on ``cfg.sample_pixels`` pixels drawn per model.

    Each model's target map may have its own resolution h×w; a sampled feature
    pixel reads the rendered query of the image pixel whose centre is nearest.

    Args:
      queries: [H, W, Q] rendered queries.
      targets: {name: [h, w, D]} feature maps (all-zero vector = no target).
      heads, banks: per model attention params and [M, D] PSC entries.
    Returns:
      (total, {"feat_<name>_l2", "feat_<name>_cos"}).
    """
    height, width = queries.shape[:2]
    total, terms = 0.0, {}
    for model_index, (name, channels) in enumerate(cfg.slices()):
        target = targets[name]
        fh, fw = target.shape[:2]
        count = fh * fw if cfg.sample_pixels <= 0 else min(cfg.sample_pixels, fh * fw)
        if count < fh * fw:
            pick = stratified_pixels(jax.random.fold_in(key, model_index), fh * fw, count)
        else:
            pick = jnp.arange(fh * fw)
        img_row, img_col = image_pixel_of(pick // fw, pick % fw, (fh, fw), (height, width))
        q = queries[img_row, img_col][:, channels]
        head, bank = heads[name], banks[name]
        predicted = attend(head, q, precompute_keys(head, bank), bank)  # keys once per step
        t = target.reshape(-1, target.shape[-1])[pick].astype(jnp.float32)
        loss, parts = feature_loss(predicted, t, jnp.any(t != 0, axis=-1))
        total = total + loss
        terms[f"feat_{name}_l2"] = parts["l2"]
        terms[f"feat_{name}_cos"] = parts["cos"]
    return total, terms
