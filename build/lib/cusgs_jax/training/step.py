"""One jitted training step: decode → rasterize → loss → masked optax update → statistics.

``make_train_step(cfg, tx, strategies)`` closes over the static configuration
(nothing in it is traced) and returns ``step(state, batch) -> (state, metrics)``,
jitted with the state donated. Naming (:mod:`cusgs_jax.types`): A anchor
capacity, S visible slots, N offsets, G = S·N, H×W image.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cusgs_jax import losses
from cusgs_jax.config import Config
from cusgs_jax.densify.base import Strategy, ViewRecord
from cusgs_jax.model.decode import decode_view, num_visible_slots
from cusgs_jax.model.field import sampled_feature_loss
from cusgs_jax.training.render import render_gaussians, view_queries
from cusgs_jax.training.state import TrainState


def _loss_fn(cfg: Config):
    """``loss(trainable, delta, anchors, batch, key) -> (loss, aux)`` for the configuration."""
    features = cfg.features

    def loss_fn(trainable, delta, anchors, batch, key):
        anchors = anchors.replace(params=trainable["anchor"])
        camera = batch["camera"]
        gaussians, view = decode_view(trainable, anchors, camera, batch["index"], cfg.model)
        queries = None
        if features.enabled:  # static: a scene without feature models traces none of this
            queries = view_queries(trainable, anchors, view, camera, batch["index"], cfg)
        out = render_gaussians(gaussians, camera, cfg.splat, delta, queries)
        loss, terms = losses.image_loss(out.image[..., :3], batch["image"], gaussians.scales, gaussians.active,
                                        l1_weight=cfg.loss.l1_weight, ssim_weight=cfg.loss.ssim_weight,
                                        volume_weight=cfg.loss.volume_weight)
        if features.enabled:
            feature_total, feature_terms = sampled_feature_loss(out.image[..., 3:], batch["features"],
                                                                trainable["memory"], batch["banks"], key, features)
            loss = loss + features.weight * feature_total
            terms.update(feature_terms, feature=feature_total)
        return loss, (out, gaussians, view, terms)

    return loss_fn


def make_train_step(cfg: Config, tx, strategies: tuple[Strategy, ...]):
    """One jitted, state-donating training step.

    The returned ``step(state, batch)`` takes ``batch = {"image": [H, W, 3]
    float32 in [0, 1], "camera": Camera, "index": [] int32 (training-view index
    for the appearance embedding)}`` plus, with feature models, ``"features":
    {model: [h, w, D]}`` and ``"banks": {model: [M, D]}``, and returns
    ``(state, metrics)``. A non-finite loss or gradient leaves the parameters
    and optimiser state untouched and increments ``state.skipped``. Every
    strategy's ``accumulate`` hook sees the view (:class:`ViewRecord`).

    **No truncated step.** When the view has more visible anchors than the
    static visible slots or more tile pairs than the pair capacity, the step
    changes nothing at all (not even ``state.step``) and reports the shortfall
    in ``metrics["dropped_anchors"]`` / ``metrics["dropped_pairs"]``; the caller
    grows the capacity and replays the same batch
    (:mod:`cusgs_jax.training.capacity`).
    """
    loss_fn = _loss_fn(cfg)

    def step(state: TrainState, batch):
        camera = batch["camera"]
        capacity = state.anchors.capacity
        delta = jnp.zeros((num_visible_slots(capacity, cfg.model.visible_fraction) * cfg.model.n_offsets, 2),
                          jnp.float32)
        key = jax.random.fold_in(jax.random.PRNGKey(cfg.train.seed), state.step)
        trainable = state.trainable
        (loss, (out, gaussians, view, terms)), (grads, grad2d) = jax.value_and_grad(
            loss_fn, argnums=(0, 1), has_aux=True)(trainable, delta, state.anchors, batch, key)
        finite = jnp.isfinite(loss) & jnp.all(jnp.array(
            [jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads)]))
        complete = (view.overflow == 0) & (out.overflow == 0)  # nothing was left out of this view
        apply = finite & complete
        updates, new_opt = tx.update(grads, state.opt_state, trainable)
        # dead anchor slots never move (their Adam moments may still be non-zero)
        alive = state.anchors.alive
        updates["anchor"] = jax.tree_util.tree_map(
            lambda u: jnp.where(alive.reshape((-1,) + (1,) * (u.ndim - 1)), u, 0.0), updates["anchor"])
        new_trainable = jax.tree_util.tree_map(lambda p, u: p + u, trainable, updates)
        keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(apply, a, b), new, old)  # noqa: E731
        record = ViewRecord(slots=view, gaussians=gaussians, render=out, grad2d=grad2d,
                            latent_grad=grads["anchor"].latent[view.slots], capacity=capacity,
                            width=camera.width, height=camera.height, step=state.step, finite=apply)
        densify = {s.name: s.accumulate(state.densify[s.name], record) for s in strategies}  # gated by record.finite
        mse = jnp.mean((jnp.clip(out.image[..., :3], 0, 1) - batch["image"]) ** 2)
        new_state = state.with_trainable(keep(new_trainable, trainable)).replace(
            opt_state=keep(new_opt, state.opt_state), densify=densify, step=state.step + complete.astype(jnp.int32),
            skipped=state.skipped + (complete & ~finite).astype(jnp.int32))
        metrics = dict(loss=loss, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)), finite=finite,
                       visible_anchors=jnp.sum(view.valid), dropped_anchors=view.overflow,
                       pairs=out.num_pairs, dropped_pairs=out.overflow,
                       loss_image=terms["loss"], **{f"loss_{k}": v for k, v in terms.items() if k != "loss"})
        return new_state, metrics

    return jax.jit(step, donate_argnums=0)
