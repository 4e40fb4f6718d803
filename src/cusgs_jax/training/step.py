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

    With ``train.batch_size = B > 1`` every per-view entry has a leading view
    axis (``image`` [B, H, W, 3], ``camera.K`` [B, 3, 3], ``camera.world_to_camera``
    [B, 4, 4], ``index`` [B], ``features`` {model: [B, h, w, D]}; ``banks``
    shared) and the step is :func:`make_batched_step`'s.

    **No truncated step.** When the view has more visible anchors than the
    static visible slots or more tile pairs than the pair capacity, the step
    changes nothing at all (not even ``state.step``) and reports the shortfall
    in ``metrics["dropped_anchors"]`` / ``metrics["dropped_pairs"]``; the caller
    grows the capacity and replays the same batch
    (:mod:`cusgs_jax.training.capacity`).
    """
    if cfg.train.batch_size > 1:
        return make_batched_step(cfg, tx, strategies)
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
        finite = _all_finite(loss, grads)
        complete = (view.overflow == 0) & (out.overflow == 0)  # nothing was left out of this view
        record = ViewRecord(slots=view, gaussians=gaussians, render=out, grad2d=grad2d,
                            latent_grad=grads["anchor"].latent[view.slots], capacity=capacity,
                            width=camera.width, height=camera.height, step=state.step, finite=finite & complete)
        densify = {s.name: s.accumulate(state.densify[s.name], record) for s in strategies}  # gated by record.finite
        mse = jnp.mean((jnp.clip(out.image[..., :3], 0, 1) - batch["image"]) ** 2)
        metrics = dict(loss=loss, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)), finite=finite,
                       visible_anchors=jnp.sum(view.valid), dropped_anchors=view.overflow,
                       pairs=out.num_pairs, dropped_pairs=out.overflow,
                       loss_image=terms["loss"], **{f"loss_{k}": v for k, v in terms.items() if k != "loss"})
        return _apply(state, tx, grads, finite, complete, densify), metrics

    return jax.jit(step, donate_argnums=0)


def _all_finite(loss, grads) -> jax.Array:
    return jnp.isfinite(loss) & jnp.all(jnp.array([jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads)]))


def _apply(state: TrainState, tx, grads, finite, complete, densify) -> TrainState:
    """The masked optax update: applied only when finite and complete; dead anchor slots never move."""
    apply = finite & complete
    trainable = state.trainable
    updates, new_opt = tx.update(grads, state.opt_state, trainable)
    # dead anchor slots never move (their Adam moments may still be non-zero)
    alive = state.anchors.alive
    updates["anchor"] = jax.tree_util.tree_map(
        lambda u: jnp.where(alive.reshape((-1,) + (1,) * (u.ndim - 1)), u, 0.0), updates["anchor"])
    new_trainable = jax.tree_util.tree_map(lambda p, u: p + u, trainable, updates)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(apply, a, b), new, old)  # noqa: E731
    return state.with_trainable(keep(new_trainable, trainable)).replace(
        opt_state=keep(new_opt, state.opt_state), densify=densify, step=state.step + complete.astype(jnp.int32),
        skipped=state.skipped + (complete & ~finite).astype(jnp.int32))


def make_batched_step(cfg: Config, tx, strategies: tuple[Strategy, ...]):
    """The step on B = ``train.batch_size`` views, sharded over the views mesh (B > 1).

    ``step(state, batch)`` with the batch of :func:`make_train_step` (leading view axis B).
    Every view is rendered and differentiated on its own device (``shard_map`` over the
    ``"views"`` axis of :func:`cusgs_jax.training.parallel.view_mesh`, B/D views per device,
    one after another with ``lax.map``: one view's intermediates in memory at a time, and the
    same per-view program as on another device count — ``vmap`` measured further apart);
    the loss is the mean of the B view losses, its gradient the mean of theirs (a ``psum``
    over the mesh), applied once by the replicated optimiser. Each view's record — its own
    ∂L_b/∂μ_2D and ∂L_b/∂z, as a single-view step would see them — is added to the
    densification statistics in view order, so growing and pruning count every view
    (gsplat's strategies rescale the batch-mean gradient by the number of cameras for the
    same reason). The step is complete only when no view dropped work; the metrics report
    the worst view's shortfall. The view-b key is ``fold_in(key(step), b)``.

    Inputs are placed on the mesh before the jitted call (state replicated, views split), so
    arrays coming back from host-side growing and pruning never change the compiled step.
    """
    from jax.sharding import PartitionSpec as P

    from cusgs_jax.training import parallel

    loss_fn = _loss_fn(cfg)
    mesh = parallel.view_mesh(cfg)
    batch_size = cfg.train.batch_size

    def local_views(trainable, anchors, views, banks, keys, deltas):
        """On one device: its B/D views' losses, aux and own gradients, and the gradient sum over the mesh."""
        def one(view, key, delta):
            batch = dict(view, banks=banks) if banks is not None else view
            return jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(trainable, delta, anchors, batch, key)

        (loss, aux), (grads, grad2d) = jax.lax.map(lambda args: one(*args), (views, keys, deltas))
        latent_grad = jax.vmap(lambda g, slots: g[slots])(grads["anchor"].latent, aux[2].slots)
        total = jax.tree_util.tree_map(lambda g: jax.lax.psum(jnp.sum(g, axis=0), parallel.AXIS), grads)
        return loss, aux, grad2d, latent_grad, total

    sharded = jax.shard_map(local_views, mesh=mesh, in_specs=(P(), P(), P(parallel.AXIS), P(), P(parallel.AXIS),
                                                              P(parallel.AXIS)),
                            out_specs=(P(parallel.AXIS),) * 4 + (P(),),
                            check_vma=False)  # the splatter's scans carry values that vary over views

    def step(state: TrainState, batch):
        camera = batch["camera"]
        capacity = state.anchors.capacity
        num_gaussians = num_visible_slots(capacity, cfg.model.visible_fraction) * cfg.model.n_offsets
        deltas = jnp.zeros((batch_size, num_gaussians, 2), jnp.float32)
        key = jax.random.fold_in(jax.random.PRNGKey(cfg.train.seed), state.step)
        keys = jax.vmap(lambda b: jax.random.fold_in(key, b))(jnp.arange(batch_size))
        views = {k: v for k, v in batch.items() if k != "banks"}
        losses, (out, gaussians, view, terms), grad2d, latent_grad, total = sharded(
            state.trainable, state.anchors, views, batch.get("banks"), keys, deltas)
        loss = jnp.mean(losses)
        grads = jax.tree_util.tree_map(lambda g: g / batch_size, total)
        finite = _all_finite(loss, grads)
        complete = jnp.all(view.overflow == 0) & jnp.all(out.overflow == 0)
        densify = dict(state.densify)
        for b in range(batch_size):  # statistics of every view, in view order (static unroll)
            pick = lambda tree: jax.tree_util.tree_map(lambda x: x[b], tree)  # noqa: E731, B023
            record = ViewRecord(slots=pick(view), gaussians=pick(gaussians), render=pick(out), grad2d=grad2d[b],
                                latent_grad=latent_grad[b], capacity=capacity, width=camera.width,
                                height=camera.height, step=state.step, finite=finite & complete)
            densify = {s.name: s.accumulate(densify[s.name], record) for s in strategies}
        mse = jnp.mean((jnp.clip(out.image[..., :3], 0, 1) - batch["image"]) ** 2)
        metrics = dict(loss=loss, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)), finite=finite,
                       visible_anchors=jnp.max(jnp.sum(view.valid, axis=-1)), dropped_anchors=jnp.max(view.overflow),
                       pairs=jnp.max(out.num_pairs), dropped_pairs=jnp.max(out.overflow),
                       loss_image=jnp.mean(terms["loss"]),
                       **{f"loss_{k}": jnp.mean(v) for k, v in terms.items() if k != "loss"})
        return _apply(state, tx, grads, finite, complete, densify), metrics

    jitted = jax.jit(step, donate_argnums=0)

    def placed_step(state: TrainState, batch):
        state, batch = parallel.place_step_inputs(mesh, state, batch)
        return jitted(state, batch)

    placed_step.jitted = jitted  # for compile counts (``jitted._cache_size()``)
    placed_step.mesh = mesh
    return placed_step
