"""One jitted training step: decode → rasterize → loss → masked optax update.

``make_train_step(cfg, ...)`` closes over the static configuration (nothing in
it is traced) and returns ``step(state, batch) -> (state, metrics)``, jitted
with the state donated. Shapes: A anchor capacity, N offsets, H×W image.

The Hydra entry point lives in :mod:`cusgs_jax.train_app`; ``python -m
cusgs_jax.train`` forwards to it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax import losses
from cusgs_jax.decode import DecoderConfig, Gaussians, decode_gaussians, frustum_mask, init_decoder
from cusgs_jax.feature_field import (FeatureConfig, decode_queries, feature_loss, init_memory_heads,
                                     init_query_heads, retrieve)
from cusgs_jax.grow_prune import GrowConfig, GrowStats, accumulate_stats
from cusgs_jax.memory.attention import attend, precompute_keys
from cusgs_jax.optim import OptimConfig, make_optimizer
from cusgs_jax.prune import PruneConfig, PruneStats, accumulate_prune_stats, prune_pass, stats_window
from cusgs_jax.scaffold import AnchorParams, Anchors, init_anchors
from cusgs_jax.splat import rasterize


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    voxel_size: float = 0.05
    n_offsets: int = 10
    latent_dim: int = 32
    hidden: int = 32
    appearance: bool = True
    appearance_dim: int = 32
    capacity_factor: float = 2.0
    frustum_margin: float = 0.15
    # Anchors in the view frustum are gathered into ceil(visible_fraction · A)
    # slots before decoding, so culled anchors cost nothing; more visible
    # anchors than that are dropped for the step and counted in
    # ``visible_overflow``. 1.0 decodes every slot (never drops).
    visible_fraction: float = 0.6
    # feature queries: "per_anchor" (hierarchical q_v → q_{v,n}) or "per_gaussian" (ablation)
    query_granularity: str = "per_anchor"

    def decoder(self) -> DecoderConfig:
        return DecoderConfig(self.n_offsets, self.latent_dim, self.hidden,
                             self.appearance_dim if self.appearance else 0)


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    tile_size: int = 8
    chunk_size: int = 16
    max_pairs_per_gaussian: float = 3.0
    antialiased: bool = False
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class LossConfig:
    l1_weight: float = 0.8
    ssim_weight: float = 0.2
    volume_weight: float = 0.01


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything the step depends on (static)."""

    iterations: int = 30_000
    seed: int = 0
    model: ModelConfig = ModelConfig()
    splat: SplatConfig = SplatConfig()
    loss: LossConfig = LossConfig()
    optim: OptimConfig = OptimConfig()
    grow: GrowConfig = GrowConfig()
    features: FeatureConfig = FeatureConfig()
    prune: PruneConfig = PruneConfig()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """Everything that changes during training (a pytree; checkpointed whole).

    Attributes:
      params: {"anchor": AnchorParams, "decoder": {...}, "appearance": [V, E]?}.
      opt_state: optax state.
      anchors: centres and alive mask.
      stats: growing statistics.
      prune: feature-aware pruning statistics since the last pruning pass
        (all zero and never updated unless ``prune.strategy == "feature_aware"``).
      step: [] int32.
      skipped: [] int32 updates skipped because loss or gradient was not finite.
    """

    params: dict
    opt_state: Any
    anchors: Anchors
    stats: GrowStats
    prune: PruneStats
    step: jax.Array
    skipped: jax.Array


def init_params(key, cfg: TrainConfig, anchor_params: AnchorParams, num_train_views: int,
                banks: dict | None = None) -> dict:
    """Parameter tree; the feature heads exist only when feature models are configured."""
    params = {"anchor": anchor_params, "decoder": init_decoder(key, cfg.model.decoder())}
    if cfg.model.appearance:
        # Scaffold-GS: nn.Embedding default init N(0, 1).
        params["appearance"] = jax.random.normal(jax.random.fold_in(key, 1),
                                                 (num_train_views, cfg.model.appearance_dim))
    if cfg.features.enabled:
        if banks is None or set(banks) != {m.name for m in cfg.features.models}:
            raise ValueError("feature models are configured: pass one PSC bank per model")
        params["queries"] = init_query_heads(
            jax.random.fold_in(key, 2), cfg.features, cfg.model.latent_dim,
            cfg.model.appearance_dim if cfg.model.appearance else 0, cfg.model.n_offsets,
            anchor_params.offsets.shape[0])
        params["memory"] = init_memory_heads(jax.random.fold_in(key, 3), cfg.features, banks)
    return params


def init_train_state(cfg: TrainConfig, points: np.ndarray, num_train_views: int, extent: float,
                     banks: dict | None = None):
    """Fresh state and optimiser from an SfM point cloud.

    Args:
      banks: {model: [S, D] PSC entries} when feature models are configured.
    Returns:
      (TrainState, optax transformation).
    """
    anchor_params, anchors = init_anchors(points, cfg.model.voxel_size, n_offsets=cfg.model.n_offsets,
                                          latent_dim=cfg.model.latent_dim,
                                          capacity_factor=cfg.model.capacity_factor)
    params = init_params(jax.random.PRNGKey(cfg.seed), cfg, anchor_params, num_train_views, banks)
    tx = make_optimizer(cfg.optim, params, cfg.iterations, extent)
    state = TrainState(params=params, opt_state=tx.init(params), anchors=anchors,
                       stats=GrowStats.zeros(anchors.capacity, cfg.model.n_offsets),
                       prune=PruneStats.zeros(anchors.capacity), step=jnp.int32(0), skipped=jnp.int32(0))
    return state, tx


def camera_center(viewmat: jax.Array) -> jax.Array:
    """[3] world position of a world→camera [4,4] matrix."""
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


def num_visible_slots(capacity: int, cfg: TrainConfig) -> int:
    """Static number of anchor slots decoded per view: ceil(visible_fraction · A), at least 1."""
    return max(1, min(capacity, int(-(-cfg.model.visible_fraction * capacity // 1))))


def visible_slots(anchors: Anchors, viewmat, K, width: int, height: int, cfg: TrainConfig):
    """Slots of the anchors to decode for a view, compacted to a static count.

    Returns:
      (slots [V] int32 indices into the anchor arrays, valid [V] bool,
      overflow [] int32 visible anchors that did not fit), V = ceil(visible_fraction · A).
    """
    capacity = anchors.capacity
    visible = frustum_mask(anchors.centers, viewmat, K, width, height, margin=cfg.model.frustum_margin)
    visible = visible & anchors.alive
    count = num_visible_slots(capacity, cfg)
    if count >= capacity:
        return jnp.arange(capacity, dtype=jnp.int32), visible, jnp.int32(0)
    (slots,) = jnp.nonzero(visible, size=count, fill_value=0)
    valid = jnp.arange(count) < jnp.sum(visible)
    return slots.astype(jnp.int32), valid, jnp.maximum(jnp.sum(visible) - count, 0).astype(jnp.int32)


def decode_view(params: dict, anchors: Anchors, viewmat, K, width: int, height: int, appearance_index,
                cfg: TrainConfig):
    """Frustum-cull the anchors, gather the visible ones and decode the view's Gaussians.

    Returns:
      (Gaussians with G = V·N, slots [V] int32, valid [V] bool, overflow []).
    """
    slots, valid, overflow = visible_slots(anchors, viewmat, K, width, height, cfg)
    anchor_params = jax.tree_util.tree_map(lambda x: x[slots], params["anchor"])
    subset = Anchors(anchors.centers[slots], anchors.alive[slots] & valid)
    appearance = params["appearance"][appearance_index] if cfg.model.appearance else None
    gaussians = decode_gaussians(params["decoder"], anchor_params, subset, camera_center(viewmat),
                                 appearance, valid, cfg.model.decoder())
    return gaussians, slots, valid, overflow


def view_queries(params: dict, anchors: Anchors, slots, viewmat, appearance_index, cfg: TrainConfig):
    """[V·N, Q] per-Gaussian feature queries of the decoded (gathered) anchors."""
    centers = anchors.centers[slots]
    direction = centers - camera_center(viewmat)
    direction = direction / jnp.maximum(jnp.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
    appearance = params["appearance"][appearance_index] if cfg.model.appearance else None
    return decode_queries(params["queries"], params["anchor"].latent[slots], direction, appearance,
                          params["anchor"].offsets[slots], slots, cfg.features)


def render_gaussians(gaussians: Gaussians, viewmat, K, width: int, height: int, cfg: TrainConfig,
                     means2d_delta=None, extra_channels=None):
    """Rasterise decoded Gaussians with the configured splatter settings.

    Args:
      extra_channels: [G, Q] or None, composited in the same pass after RGB
        (background 0), e.g. the feature queries.
    """
    num = gaussians.means.shape[0]
    colors, background = gaussians.colors, jnp.asarray(cfg.splat.background, jnp.float32)
    if extra_channels is not None:
        colors = jnp.concatenate([colors, extra_channels], axis=-1)
        background = jnp.concatenate([background, jnp.zeros(extra_channels.shape[-1], jnp.float32)])
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, colors,
                     viewmat, K, width, height, background=background,
                     antialiased=cfg.splat.antialiased, tile_size=cfg.splat.tile_size,
                     chunk_size=cfg.splat.chunk_size,
                     max_pairs=int(cfg.splat.max_pairs_per_gaussian * num) + 4096,
                     means2d_delta=means2d_delta)


def make_render_fn(cfg: TrainConfig, width: int, height: int):
    """Jitted ``render(params, anchors, viewmat, K, appearance_index) -> [H, W, 3]`` for evaluation."""

    @jax.jit
    def render(params, anchors, viewmat, K, appearance_index):
        gaussians, *_ = decode_view(params, anchors, viewmat, K, width, height, appearance_index, cfg)
        out = render_gaussians(gaussians, viewmat, K, width, height, cfg)
        return jnp.clip(out.image, 0.0, 1.0), out.overflow

    return render


def make_feature_render_fn(cfg: TrainConfig, width: int, height: int):
    """Jitted ``render(params, anchors, viewmat, K, appearance_index, banks) -> (rgb [H,W,3], {model: [H,W,D]})``."""

    @jax.jit
    def render(params, anchors, viewmat, K, appearance_index, banks):
        gaussians, slots, _, _ = decode_view(params, anchors, viewmat, K, width, height, appearance_index, cfg)
        queries = view_queries(params, anchors, slots, viewmat, appearance_index, cfg)
        out = render_gaussians(gaussians, viewmat, K, width, height, cfg, extra_channels=queries)
        features = retrieve(params["memory"], banks, out.image[..., 3:], cfg.features)
        return jnp.clip(out.image[..., :3], 0.0, 1.0), features

    return render


def make_train_step(cfg: TrainConfig, tx, width: int, height: int):
    """One jitted, state-donating training step.

    The returned ``step(state, batch)`` takes ``batch = {"image": [H, W, 3]
    float32 in [0, 1], "viewmat": [4, 4], "K": [3, 3], "index": [] int32
    (training-view index for the appearance embedding)}`` and returns
    ``(state, metrics)``. A non-finite loss or gradient leaves params and
    optimiser state untouched and increments ``state.skipped``.
    """
    n = cfg.model.n_offsets
    grow = cfg.grow

    features = cfg.features

    def loss_fn(params, delta, anchors, batch, key):
        gaussians, slots, valid, overflow = decode_view(params, anchors, batch["viewmat"], batch["K"], width,
                                                        height, batch["index"], cfg)
        queries = None
        if features.enabled:  # static: a scene without feature models traces none of this
            queries = view_queries(params, anchors, slots, batch["viewmat"], batch["index"], cfg)
        out = render_gaussians(gaussians, batch["viewmat"], batch["K"], width, height, cfg, delta, queries)
        rgb = out.image[..., :3]
        loss, terms = losses.image_loss(rgb, batch["image"], gaussians.scales, gaussians.active,
                                        l1_weight=cfg.loss.l1_weight, ssim_weight=cfg.loss.ssim_weight,
                                        volume_weight=cfg.loss.volume_weight)
        if features.enabled:
            feature_total = 0.0
            for model_index, (name, channels) in enumerate(features.slices()):
                target = batch["features"][name]  # [h, w, D] at the feature-map resolution
                fh, fw = target.shape[:2]
                count = fh * fw if features.sample_pixels <= 0 else min(features.sample_pixels, fh * fw)
                if count < fh * fw:
                    pick = jax.random.choice(jax.random.fold_in(key, model_index), fh * fw, (count,),
                                             replace=False)
                else:
                    pick = jnp.arange(fh * fw)
                row, col = pick // fw, pick % fw
                # the image pixel whose centre is nearest to the feature pixel's centre
                img_row = jnp.minimum(((row + 0.5) * height / fh).astype(jnp.int32), height - 1)
                img_col = jnp.minimum(((col + 0.5) * width / fw).astype(jnp.int32), width - 1)
                q = out.image[img_row, img_col, 3:][:, channels]
                head, bank = params["memory"][name], batch["banks"][name]
                predicted = attend(head, q, precompute_keys(head, bank), bank)  # keys once per step
                t = target.reshape(-1, target.shape[-1])[pick].astype(jnp.float32)
                f_loss, f_terms = feature_loss(predicted, t, jnp.any(t != 0, axis=-1))
                feature_total = feature_total + f_loss
                terms[f"feat_{name}_l2"] = f_terms["l2"]
                terms[f"feat_{name}_cos"] = f_terms["cos"]
            loss = loss + features.weight * feature_total
            terms["feature"] = feature_total
        return loss, (out, gaussians, slots, valid, overflow, terms)

    def step(state: TrainState, batch):
        capacity = state.anchors.capacity
        delta = jnp.zeros((num_visible_slots(capacity, cfg) * n, 2), jnp.float32)
        key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), state.step)
        (loss, (out, gaussians, slots, valid, vis_overflow, terms)), (grads, grad2d) = jax.value_and_grad(
            loss_fn, argnums=(0, 1), has_aux=True)(state.params, delta, state.anchors, batch, key)
        finite = jnp.isfinite(loss) & jnp.all(jnp.array(
            [jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads)]))
        updates, new_opt = tx.update(grads, state.opt_state, state.params)
        # dead anchor slots never move (their Adam moments may still be non-zero)
        alive = state.anchors.alive
        updates["anchor"] = jax.tree_util.tree_map(
            lambda u: jnp.where(alive.reshape((-1,) + (1,) * (u.ndim - 1)), u, 0.0), updates["anchor"])
        new_params = jax.tree_util.tree_map(lambda p, u: p + u, state.params, updates)
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, old)  # noqa: E731
        in_window = (state.step >= grow.stats_start) & (state.step < grow.stop)
        # scatter the compacted per-view quantities back to anchor slots
        def to_slots(x, fill=0):
            full = jnp.full((capacity,) + x.shape[1:], fill, x.dtype)
            return full.at[jnp.where(valid, slots, capacity)].set(x, mode="drop")

        stats = accumulate_stats(
            state.stats, to_slots(valid, False), to_slots(gaussians.opacities.reshape(-1, n)),
            to_slots((gaussians.active & out.visible).reshape(-1, n), False),
            to_slots(grad2d.reshape(-1, n, 2)), width, height, in_window & finite)
        prune_stats = state.prune
        if cfg.prune.strategy == "feature_aware":  # static: other strategies trace none of this
            # ‖∇_z L‖ of this step's loss for every decoded anchor, and the splatter's
            # per-Gaussian Σ opacity·T with LightGaussian's volume weight (prune.py).
            prune_stats = accumulate_prune_stats(
                state.prune, slots, valid, grads["anchor"].latent[slots], out.significance, gaussians.scales,
                gaussians.active, stats_window(state.step, cfg.prune) & finite, cfg.prune)
        mse = jnp.mean((jnp.clip(out.image[..., :3], 0, 1) - batch["image"]) ** 2)
        new_state = TrainState(
            params=keep(new_params, state.params), opt_state=keep(new_opt, state.opt_state),
            anchors=state.anchors, stats=stats, prune=prune_stats, step=state.step + 1,
            skipped=state.skipped + (~finite).astype(jnp.int32))
        metrics = dict(loss=loss, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)), finite=finite,
                       visible_anchors=jnp.sum(valid), visible_overflow=vis_overflow, overflow=out.overflow,
                       **{f"loss_{k}": v for k, v in terms.items() if k != "loss"})
        return new_state, metrics

    return jax.jit(step, donate_argnums=0)


def make_prune_step(cfg: TrainConfig):
    """Jitted ``prune(state) -> (state, info)``: one feature-aware pruning pass between steps.

    Clears the ``alive`` bit of the lowest-scoring ``floor(prune.ratio · alive)``
    anchors (:func:`cusgs_jax.prune.prune_pass`) and resets the pruning
    statistics. Shapes are unchanged, so neither this function nor the train
    step recompiles; a dead slot is skipped by the frustum gather, receives no
    update (the step masks anchor updates by ``alive``) and may later be
    refilled by growing. ``info``: {"pruned", "alive", "candidates"} int32.
    For strategies other than "feature_aware" the anchors are unchanged.
    """

    def prune(state: TrainState):
        anchors, stats, info = prune_pass(state.anchors, state.params["anchor"].latent, state.prune, cfg.prune)
        return dataclasses.replace(state, anchors=anchors, prune=stats), info

    return jax.jit(prune, donate_argnums=0)


def compact_for_render(params: dict, anchors: Anchors, multiple: int = 64):
    """Drop dead anchor slots so rendering pays only for alive anchors.

    Gathers the alive slots (in slot order) of every per-anchor array
    (``params["anchor"]``, a per-Gaussian query table) into a capacity of
    ``alive`` rounded up to ``multiple`` (few distinct shapes, few compiles);
    the padding slots are dead. Render the result with
    ``model.visible_fraction = 1.0`` (:func:`render_config`) so no visible
    anchor is dropped. Host-side, outside jit.

    Returns:
      (params, anchors) with capacity ``A' = ceil(alive / multiple) · multiple``.
    """
    alive = np.asarray(anchors.alive)
    keep = np.flatnonzero(alive)
    new_capacity = max(multiple, -(-len(keep) // multiple) * multiple)
    index = np.concatenate([keep, np.full(new_capacity - len(keep), keep[0] if len(keep) else 0)])
    live = np.arange(new_capacity) < len(keep)

    def gather(x):
        return jnp.asarray(x)[index]

    params = dict(params, anchor=jax.tree_util.tree_map(gather, params["anchor"]))
    if "queries" in params and "table" in params["queries"]:
        params["queries"] = dict(params["queries"], table=gather(params["queries"]["table"]))
    return params, Anchors(gather(anchors.centers), jnp.asarray(live))


def render_config(cfg: TrainConfig) -> TrainConfig:
    """The config for rendering a :func:`compact_for_render` model (every slot decoded)."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, visible_fraction=1.0))


def main() -> None:  # pragma: no cover - thin forwarder
    from cusgs_jax.train_app import main as app_main

    app_main()


if __name__ == "__main__":  # pragma: no cover
    main()
