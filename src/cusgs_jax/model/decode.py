"""Anchor decoding: (latent, view direction, appearance) → N Gaussians per anchor.

Scaffold-GS ``generate_neural_gaussians`` (docs/method.md#decoding), in plain JAX.
Naming (:mod:`cusgs_jax.types`): A anchors, S visible slots, N offsets per
anchor, F latent size, E appearance size, G = S·N Gaussians.

| head | input | output | activation |
|---|---|---|---|
| opacity | z, d | N | tanh; ≤ 0 switches the Gaussian off |
| covariance | z, d | 7N | scale = exp(s[3:])·sigmoid(out[:3]); quat = out[3:7] |
| colour | z, d, e | 3N | sigmoid |

Position ``μ = x_v + Δx · exp(s[:3])``.

Per view, the anchors in the frustum are first gathered into a static number
of visible slots S (:func:`visible_slots`), so culled anchors cost nothing.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cusgs_jax.config import DecoderConfig
from cusgs_jax.model.anchors import AnchorParams, AnchorState
from cusgs_jax.nn import apply_mlp, init_mlp
from cusgs_jax.scan import first_true
from cusgs_jax.splat.lens import Lens, distort, inside_bounds
from cusgs_jax.types import Camera
from cusgs_jax.precision import HIGHEST, network_precision


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
      anchor_index: [G] int32 row of the owning anchor in the decoded arrays.
    """

    means: jax.Array
    quats: jax.Array
    scales: jax.Array
    opacities: jax.Array
    colors: jax.Array
    active: jax.Array
    anchor_index: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class VisibleSlots:
    """The anchors gathered for one view.

    Attributes:
      slots: [S] int32 anchor slots (indices into the [A] arrays).
      valid: [S] bool, the entry holds an alive anchor in the frustum (padding entries repeat slot 0).
      overflow: [] int32 visible anchors that did not fit in S.
    """

    slots: jax.Array
    valid: jax.Array
    overflow: jax.Array


def frustum_mask(centers: jax.Array, viewmat: jax.Array, K: jax.Array, width: int, height: int,
                 *, near: float = 0.01, margin: float = 0.15, lens: Lens | None = None) -> jax.Array:
    """Anchors whose centre projects into the image widened by ``margin`` on each side.

    Args:
      centers: [A, 3]; viewmat: [4, 4] world→camera; K: [3, 3].
      lens: the camera's distortion, or None (pinhole). With a lens the centre is projected
        through it, and a centre outside the lens's trusted box (:mod:`cusgs_jax.splat.lens`) is
        never visible.
    Returns:
      [A] bool.
    """
    cam = jnp.matmul(centers, viewmat[:3, :3].T, precision=HIGHEST) + viewmat[:3, 3]
    z = cam[:, 2]
    zs = jnp.where(z > near, z, 1.0)
    front = z > near
    if lens is None:
        u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
        v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    else:
        uv = cam[:, :2] / zs[:, None]
        front = front & inside_bounds(lens, uv)
        uv = distort(lens, jnp.where(front[:, None], uv, 0.0))
        u, v = K[0, 0] * uv[:, 0] + K[0, 2], K[1, 1] * uv[:, 1] + K[1, 2]
    mx, my = margin * width, margin * height
    return front & (u > -mx) & (u < width + mx) & (v > -my) & (v < height + my)


def num_visible_slots(capacity: int, visible_fraction: float) -> int:
    """Static S = ceil(visible_fraction · A), at least 1 and at most A."""
    return max(1, min(capacity, int(-(-visible_fraction * capacity // 1))))


def visible_slots(anchors: AnchorState, camera: Camera, *, num_slots: int, margin: float) -> VisibleSlots:
    """Slots of the alive anchors in the camera's frustum, compacted to S = ``num_slots`` entries (static)."""
    capacity = anchors.capacity
    visible = frustum_mask(anchors.centers, camera.world_to_camera, camera.K, camera.width, camera.height,
                           margin=margin, lens=camera.lens) & anchors.alive
    if num_slots >= capacity:
        return VisibleSlots(jnp.arange(capacity, dtype=jnp.int32), visible, jnp.int32(0))
    slots = first_true(visible, num_slots)
    valid = jnp.arange(num_slots) < jnp.sum(visible)
    return VisibleSlots(slots, valid,
                        jnp.maximum(jnp.sum(visible) - num_slots, 0).astype(jnp.int32))


def to_slots(x: jax.Array, view: VisibleSlots, capacity: int, fill=0) -> jax.Array:
    """Scatter per-visible-slot values [S, ...] back to the A = ``capacity`` anchor slots (others ``fill``)."""
    full = jnp.full((capacity,) + x.shape[1:], fill, x.dtype)
    return full.at[jnp.where(view.valid, view.slots, capacity)].set(x, mode="drop")


def view_directions(centers: jax.Array, camera_center: jax.Array) -> jax.Array:
    """[S, 3] unit directions from the camera to the anchor centres [S, 3] (the decoders' view input)."""
    direction = centers - camera_center
    return direction / jnp.maximum(jnp.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewInputs:
    """What every per-anchor head sees of one view, computed once (:func:`view_inputs`) and shared
    by the Gaussian heads (:func:`decode_inputs`) and the feature-query heads
    (:func:`cusgs_jax.model.queries.decode_queries`), so the two can never disagree.

    Attributes:
      rows: [S, …] learnable anchor arrays (:class:`AnchorParams`).
      centers: [S, 3] anchor centres.
      decoded: [S] bool, the anchor is alive and visible (others decode to opacity 0).
      direction: [S, 3] unit camera→anchor direction d (Scaffold-GS's view input).
      appearance: [E] the view's appearance embedding e, or None when disabled.
    """

    rows: AnchorParams
    centers: jax.Array
    decoded: jax.Array
    direction: jax.Array
    appearance: jax.Array | None


def inputs_at(rows: AnchorParams, centers: jax.Array, decoded: jax.Array, camera_center: jax.Array,
              appearance: jax.Array | None) -> ViewInputs:
    """:class:`ViewInputs` of anchors [S] seen from ``camera_center`` [3] (appearance [E] or None)."""
    return ViewInputs(rows, centers, decoded, view_directions(centers, camera_center), appearance)


def view_inputs(nets: dict, rows: AnchorParams, centers: jax.Array, decoded: jax.Array, camera: Camera,
                appearance_index: jax.Array, cfg) -> ViewInputs:
    """:class:`ViewInputs` of gathered anchor rows (:func:`gather_visible`) at ``camera``.

    Args:
      nets: {"appearance"?: [V, E], …}; appearance_index: [] int32 training view;
      cfg: :class:`cusgs_jax.config.ModelConfig` (static).
    """
    appearance = nets["appearance"][appearance_index] if cfg.appearance else None
    return inputs_at(rows, centers, decoded, camera.center, appearance)


def decode_inputs(params: dict, inputs: ViewInputs, cfg: DecoderConfig) -> Gaussians:
    """Decode the N Gaussians of every anchor of ``inputs`` (S anchors → G = S·N Gaussians).

    Args:
      params: decoder params from :func:`init_decoder`.
      inputs: the view's :class:`ViewInputs` (the query table of ``rows`` is not used here).
    Returns:
      :class:`Gaussians` with G = S·N; anchors not ``decoded`` produce opacity 0 (and no
      rasterisation work).
    """
    rows, centers = inputs.rows, inputs.centers
    num, n = centers.shape[0], cfg.n_offsets
    base = jnp.concatenate([rows.latent, inputs.direction], axis=-1)  # [S, F+3]
    precision = network_precision(cfg.matmul_precision)
    opacity = jnp.tanh(apply_mlp(params["opacity"], base, precision))  # [S, N]
    cov = apply_mlp(params["cov"], base, precision).reshape(num, n, 7)
    appearance = inputs.appearance
    if appearance is not None:
        color_in = jnp.concatenate([base, jnp.broadcast_to(appearance, (num, appearance.shape[-1]))], axis=-1)
    else:
        color_in = base
    colors = jax.nn.sigmoid(apply_mlp(params["color"], color_in, precision)).reshape(num, n, 3)

    scaling = jnp.exp(rows.log_scaling)  # [S, 6]
    scales = scaling[:, None, 3:] * jax.nn.sigmoid(cov[..., :3])
    quats = cov[..., 3:7]
    means = centers[:, None, :] + rows.offsets * scaling[:, None, :3]
    keep = inputs.decoded[:, None] & (opacity > 0)
    return Gaussians(
        means=means.reshape(-1, 3),
        quats=quats.reshape(-1, 4),
        scales=scales.reshape(-1, 3),
        opacities=jnp.where(keep, opacity, 0.0).reshape(-1),
        colors=colors.reshape(-1, 3),
        active=keep.reshape(-1),
        anchor_index=jnp.repeat(jnp.arange(num, dtype=jnp.int32), n),
    )


def decode_gaussians(params: dict, anchor_params: AnchorParams, centers: jax.Array, decoded: jax.Array,
                     camera_center: jax.Array, appearance: jax.Array | None, cfg: DecoderConfig) -> Gaussians:
    """Decode the N Gaussians of every given anchor seen from ``camera_center``
    (:func:`decode_inputs` of :func:`inputs_at`).

    Args:
      params: decoder params from :func:`init_decoder`.
      anchor_params: [S, …] learnable anchor arrays; centers: [S, 3] anchor centres.
      decoded: [S] bool, the anchor is alive and visible.
      camera_center: [3] world position of the camera; appearance: [E] or None.
    Returns:
      :class:`Gaussians` with G = S·N.
    """
    return decode_inputs(params, inputs_at(anchor_params, centers, decoded, camera_center, appearance), cfg)


def gather_visible(anchors: AnchorState, view: VisibleSlots) -> tuple[AnchorParams, jax.Array, jax.Array]:
    """(learnable rows [S, …], centres [S, 3], decoded [S] bool) of the visible slots."""
    rows = jax.tree_util.tree_map(lambda x: x[view.slots], anchors.params)
    return rows, anchors.centers[view.slots], anchors.alive[view.slots] & view.valid


def decode_view(nets: dict, anchors: AnchorState, camera: Camera, appearance_index: jax.Array,
                cfg, num_slots: int) -> tuple[Gaussians, VisibleSlots]:
    """Frustum-cull the anchors, gather the visible ones into S = ``num_slots`` and decode the view's Gaussians.

    Args:
      nets: {"decoder", "appearance"?: [V, E]} network parameters.
      appearance_index: [] int32 training view whose appearance embedding is used.
      cfg: :class:`cusgs_jax.config.ModelConfig` (static).
      num_slots: static S (:meth:`cusgs_jax.training.capacity.Capacities.visible_slots`).
    Returns:
      (Gaussians with G = S·N in slot order, VisibleSlots).
    """
    view = visible_slots(anchors, camera, num_slots=num_slots, margin=cfg.frustum_margin)
    inputs = view_inputs(nets, *gather_visible(anchors, view), camera, appearance_index, cfg)
    return decode_inputs(nets["decoder"], inputs, cfg.decoder()), view
