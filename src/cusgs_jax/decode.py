"""Anchor decoding: (latent, view direction, appearance) → N Gaussians per anchor.

Scaffold-GS ``generate_neural_gaussians`` (DESIGN.md §1), in plain JAX.
Naming: A anchors, N offsets per anchor, F latent size, E appearance size,
G = A·N Gaussians.

| head | input | output | activation |
|---|---|---|---|
| opacity | z, d | N | tanh; ≤ 0 switches the Gaussian off |
| covariance | z, d | 7N | scale = exp(s[3:])·sigmoid(out[:3]); quat = out[3:7] |
| colour | z, d, e | 3N | sigmoid |

Position ``μ = x_v + Δx · exp(s[:3])``.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from cusgs_jax.scaffold import AnchorParams, Anchors


def init_mlp(key: jax.Array, sizes: tuple[int, ...]) -> dict:
    """Dense layers initialised like PyTorch ``nn.Linear`` (U(±1/√fan_in)).

    Returns:
      {"w0": [sizes[0], sizes[1]], "b0": [sizes[1]], "w1": …}.
    """
    params = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        key, kw, kb = jax.random.split(key, 3)
        bound = 1.0 / math.sqrt(fan_in)
        params[f"w{i}"] = jax.random.uniform(kw, (fan_in, fan_out), jnp.float32, -bound, bound)
        params[f"b{i}"] = jax.random.uniform(kb, (fan_out,), jnp.float32, -bound, bound)
    return params


def apply_mlp(params: dict, x: jax.Array) -> jax.Array:
    """Dense → ReLU → … → Dense (no final activation). x: [..., sizes[0]]."""
    layers = len(params) // 2
    for i in range(layers):
        x = x @ params[f"w{i}"] + params[f"b{i}"]
        if i < layers - 1:
            x = jax.nn.relu(x)
    return x


@dataclasses.dataclass(frozen=True)
class DecoderConfig:
    """Static decoder shape (closed over, never traced)."""

    n_offsets: int = 10
    latent_dim: int = 32
    hidden: int = 32
    appearance_dim: int = 32  # 0 disables the appearance embedding entirely


def init_decoder(key: jax.Array, cfg: DecoderConfig) -> dict:
    """The three Scaffold-GS heads: {"opacity", "cov", "color"} MLP params."""
    k1, k2, k3 = jax.random.split(key, 3)
    base = cfg.latent_dim + 3
    return {
        "opacity": init_mlp(k1, (base, cfg.hidden, cfg.n_offsets)),
        "cov": init_mlp(k2, (base, cfg.hidden, 7 * cfg.n_offsets)),
        "color": init_mlp(k3, (base + cfg.appearance_dim, cfg.hidden, 3 * cfg.n_offsets)),
    }


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gaussians:
    """Decoded Gaussians of one view.

    Attributes:
      means: [G, 3]; quats: [G, 4] (wxyz, unnormalised); scales: [G, 3];
      opacities: [G] (0 where switched off, culled or dead); colors: [G, 3];
      active: [G] bool, opacity > 0 (for statistics);
      anchor_index: [G] int32 slot of the owning anchor.
    """

    means: jax.Array
    quats: jax.Array
    scales: jax.Array
    opacities: jax.Array
    colors: jax.Array
    active: jax.Array
    anchor_index: jax.Array


def frustum_mask(centers: jax.Array, viewmat: jax.Array, K: jax.Array, width: int, height: int,
                 *, near: float = 0.01, margin: float = 0.15) -> jax.Array:
    """Anchors whose centre projects into the image widened by ``margin`` on each side.

    Args:
      centers: [A, 3]; viewmat: [4, 4]; K: [3, 3].
    Returns:
      [A] bool.
    """
    cam = centers @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    zs = jnp.where(z > near, z, 1.0)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    mx, my = margin * width, margin * height
    return (z > near) & (u > -mx) & (u < width + mx) & (v > -my) & (v < height + my)


def decode_gaussians(params: dict, anchor_params: AnchorParams, anchors: Anchors, camera_center: jax.Array,
                     appearance: jax.Array | None, visible: jax.Array, cfg: DecoderConfig) -> Gaussians:
    """Decode the N Gaussians of every anchor for one view.

    Args:
      params: decoder params from :func:`init_decoder`.
      anchor_params: [A, …] learnable anchor arrays.
      anchors: centres [A, 3] and alive mask [A].
      camera_center: [3] world position of the camera.
      appearance: [E] embedding of the view's camera, or None when disabled.
      visible: [A] bool, e.g. :func:`frustum_mask`; invisible anchors produce
        Gaussians with opacity 0 (and no rasterisation work).
    Returns:
      :class:`Gaussians` with G = A·N.
    """
    num, n = anchors.centers.shape[0], cfg.n_offsets
    direction = anchors.centers - camera_center
    direction = direction / jnp.maximum(jnp.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
    base = jnp.concatenate([anchor_params.latent, direction], axis=-1)  # [A, F+3]
    opacity = jnp.tanh(apply_mlp(params["opacity"], base))  # [A, N]
    cov = apply_mlp(params["cov"], base).reshape(num, n, 7)
    if appearance is not None:
        color_in = jnp.concatenate([base, jnp.broadcast_to(appearance, (num, appearance.shape[-1]))], axis=-1)
    else:
        color_in = base
    colors = jax.nn.sigmoid(apply_mlp(params["color"], color_in)).reshape(num, n, 3)

    scaling = jnp.exp(anchor_params.log_scaling)  # [A, 6]
    scales = scaling[:, None, 3:] * jax.nn.sigmoid(cov[..., :3])
    quats = cov[..., 3:7]
    means = anchors.centers[:, None, :] + anchor_params.offsets * scaling[:, None, :3]
    keep = (anchors.alive & visible)[:, None] & (opacity > 0)
    return Gaussians(
        means=means.reshape(-1, 3),
        quats=quats.reshape(-1, 4),
        scales=scales.reshape(-1, 3),
        opacities=jnp.where(keep, opacity, 0.0).reshape(-1),
        colors=colors.reshape(-1, 3),
        active=keep.reshape(-1),
        anchor_index=jnp.repeat(jnp.arange(num, dtype=jnp.int32), n),
    )
