"""One jitted training step: cull → decode → compact → rasterize → loss → update → statistics.

``make_train_step(cfg, tx, strategies, capacities)`` closes over the static configuration
and capacities (nothing in them is traced) and returns ``step(state, batch) -> (state,
metrics)``, jitted with the state donated. Naming (:mod:`cusgs_jax.types`): A anchor
capacity, S visible slots, N offsets, G = S·N decoded Gaussians, G_act active Gaussians,
B views per step, H×W image.

What a step pays for follows what the view shows:

* the frustum gather decodes S slots (not A);
* only the G_act Gaussians that pass the opacity mask are projected, sorted, binned and
  composited (:mod:`cusgs_jax.model.active`), with a pair capacity per active Gaussian;
* the loss is differentiated with respect to the S gathered anchor rows, so the anchors'
  gradients have S rows, and the update (``optim.sparse``, the default) touches only those
  rows of the parameters and Adam moments (gsplat's ``visible_adam``): the finite check and
  the apply-or-keep select are O(S) too. ``optim.sparse=false`` scatters the S rows into a
  dense [A] gradient and runs Adam over every alive row, as before.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax import losses
from cusgs_jax.config import Config, require_config
from cusgs_jax.densify.base import Strategy, ViewRecord
from cusgs_jax.model.active import expand_render, scatter_back
from cusgs_jax.model.anchors import is_per_anchor, map_rows
from cusgs_jax.model.decode import gather_visible, to_slots, view_inputs, visible_slots
from cusgs_jax.model.field import read_pixels, sampled_feature_loss
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.optim import group_rates, rate_arguments
from cusgs_jax.training.loss_terms import TermRender, check_loss_terms, term_weights
from cusgs_jax.training import parallel
from cusgs_jax.training.render import decode_view_inputs, render_gaussians, work_metrics
from cusgs_jax.training.state import TrainState


def loss_weights(cfg: Config, loss_terms=()) -> dict[str, np.float32]:
    """The loss terms' weights as arrays: ``{"l1", "ssim", "volume", "feature"}`` ([] float32) and one per user
    term of ``loss_terms`` (:class:`~cusgs_jax.training.loss_terms.LossTerm`, by its name).

    :func:`~cusgs_jax.training.inputs.make_batches` puts them in every batch (``"loss_weights"``), so they
    are arguments of the step's program, not constants: jobs of a sweep over ``loss.*_weight`` or
    ``features.weight`` share one compiled step. A batch without them uses these values as constants
    (the same numbers)."""
    return dict(l1=np.float32(cfg.loss.l1_weight), ssim=np.float32(cfg.loss.ssim_weight),
                volume=np.float32(cfg.loss.volume_weight), feature=np.float32(cfg.features.weight),
                **term_weights(loss_terms))


def step_settings(cfg: Config, extent: float, loss_terms=()) -> dict:
    """The settings a step takes as arguments rather than constants, in one place: ``{"loss_weights":
    {term: [] float32} (:func:`loss_weights`), "seed_key": jax.random.PRNGKey(train.seed), "learning_rates":
    {group: [2] float32} (:func:`~cusgs_jax.training.optim.rate_arguments` of the groups' rates for a scene of
    ``extent`` and ``train.batch_size``)}``.

    :func:`~cusgs_jax.training.inputs.make_batches` puts them in every batch, so jobs of a sweep that differ only
    in them share one step program; a batch without them runs with the same values folded in as constants."""
    return dict(loss_weights=jax.device_put(loss_weights(cfg, loss_terms)),
                seed_key=jax.random.PRNGKey(cfg.train.seed),
                learning_rates=rate_arguments(group_rates(cfg.optim, extent, cfg.train.batch_size)))


def _view_pass(cfg: Config, capacities: Capacities, anchor_capacity: int, loss_terms=()):
    """``one(trainable, anchors, batch, key, state) -> (loss, grads, parts)`` for one view.

    ``grads``: the trainable tree's gradient with the anchor rows of the view's S visible
    slots only ({"anchor": AnchorParams [S, …], networks dense}). ``parts``: what the record,
    the metrics and the update need (the visible slots, decoded Gaussians, the render with its
    per-Gaussian fields in decoded order, ∂L/∂μ_2D [G, 2], the loss terms (unweighted), the work counts).
    """
    model, features = cfg.model, cfg.features
    num_slots = capacities.visible_slots(anchor_capacity)
    active_capacity = capacities.active_gaussians(anchor_capacity, model.n_offsets)
    pair_capacity = capacities.pairs(anchor_capacity, model.n_offsets)

    def loss_fn(local, delta, centers, decoded, batch, key, state):
        camera = batch["camera"]
        weights = batch["loss_weights"] if "loss_weights" in batch else loss_weights(cfg, loss_terms)
        # differentiated with respect to the S gathered rows (local["anchor"]), not the [A] arrays;
        # a scene without feature models (static) traces no query head
        inputs = view_inputs(local, local["anchor"], centers, decoded, camera, batch["index"], model)
        gaussians, queries = decode_view_inputs(local, inputs, cfg, queries=features.enabled)
        # the queries only where the feature loss can read them (static: the maps' and the image's sizes)
        pixels = (read_pixels({name: target.shape[:2] for name, target in batch["features"].items()},
                              (camera.height, camera.width))
                  if features.enabled and features.sparse_queries else None)
        out, chosen = render_gaussians(gaussians, camera, cfg.splat, active_capacity=active_capacity,
                                       pair_capacity=pair_capacity, means2d_delta=delta, extra_channels=queries,
                                       extra_pixels=pixels)
        loss, terms = losses.image_loss(out.image[..., :3], batch["image"], gaussians.scales, gaussians.active,
                                        pixel_mask=batch.get("valid"), l1_weight=weights["l1"],
                                        ssim_weight=weights["ssim"], volume_weight=weights["volume"])
        if features.enabled:
            feature_total, feature_terms = sampled_feature_loss(out.image[..., 3:], batch["features"],
                                                                local["memory"], batch["banks"], key, features)
            loss = loss + weights["feature"] * feature_total
            terms.update(feature_terms, feature=feature_total)
        if loss_terms:  # research code's own terms (training/loss_terms.py), after the built-in ones
            seen = TermRender(out.image[..., :3], out.alpha, out.depth, gaussians)
            for term in loss_terms:
                value = jnp.asarray(term.fn(seen, batch, state), jnp.float32).reshape(())
                terms[term.name] = value
                loss = loss + weights[term.name] * value
        return loss, (out, gaussians, chosen, terms)

    def one(trainable, anchors, batch, key, state):
        camera = batch["camera"]
        view = visible_slots(anchors, camera, num_slots=num_slots, margin=model.frustum_margin)
        rows, centers, decoded = gather_visible(anchors.replace(params=trainable["anchor"]), view)
        local = dict(trainable, anchor=rows)
        delta = jnp.zeros((active_capacity, 2), jnp.float32)
        (loss, (out, gaussians, chosen, terms)), (grads, grad2d) = jax.value_and_grad(
            loss_fn, argnums=(0, 1), has_aux=True)(local, delta, centers, decoded, batch, key, state)
        mse = losses.masked_mean((jnp.clip(out.image[..., :3], 0, 1) - batch["image"]) ** 2, batch.get("valid"))
        parts = dict(view=view, gaussians=gaussians, render=expand_render(out, chosen),
                     grad2d=scatter_back(grad2d, chosen), terms=terms, work=work_metrics(view, chosen, out), mse=mse)
        return loss, grads, parts

    return one


def _record(parts: dict, latent_grad, capacity: int, camera, step, finite) -> ViewRecord:
    return ViewRecord(slots=parts["view"], gaussians=parts["gaussians"], render=parts["render"],
                      grad2d=parts["grad2d"], latent_grad=latent_grad, capacity=capacity,
                      width=camera.width, height=camera.height, step=step, finite=finite)


def _metrics(loss, finite, parts: dict, reduce) -> dict:
    """Step metrics; ``reduce`` folds a per-view value over the batch (identity for one view)."""
    work = parts["work"]
    mse = reduce(parts["mse"], jnp.mean)
    terms = parts["terms"]
    return dict(loss=loss, psnr=-10.0 * jnp.log10(jnp.maximum(mse, 1e-12)), finite=finite,
                **{k: reduce(v, jnp.max) for k, v in work.items()},
                loss_image=reduce(terms["loss"], jnp.mean),
                **{f"loss_{k}": reduce(v, jnp.mean) for k, v in terms.items() if k != "loss"})


def make_train_step(cfg: Config, tx, strategies: tuple[Strategy, ...], capacities: Capacities | None = None,
                    loss_terms=()):
    """One jitted, state-donating training step.

    The returned ``step(state, batch)`` takes ``batch = {"image": [H, W, 3]
    float32 in [0, 1], "camera": Camera, "index": [] int32 (training-view index
    for the appearance embedding)}`` plus, with feature models, ``"features":
    {model: [h, w, D]}`` and ``"banks": {model: [M, D]}``, and for a scene with a
    valid-pixel mask (``SceneData.valid``) ``"valid": [H, W] bool``, and returns
    ``(state, metrics)``. Optional entries make settings arguments instead of the program's
    constants (the numbers are the same; jobs that differ only in them share one program):
    ``"loss_weights"`` (:func:`loss_weights`), ``"seed_key"`` (``jax.random.PRNGKey(train.seed)``) and
    ``"learning_rates"`` (:func:`cusgs_jax.training.optim.rate_arguments`, read by ``tx`` from
    :func:`~cusgs_jax.training.optim.make_optimizer`); :func:`~cusgs_jax.training.inputs.make_batches` gives all three. A non-finite loss or gradient leaves the parameters
    and optimiser state untouched and increments ``state.skipped``. Every
    strategy's ``accumulate`` hook sees the view (:class:`ViewRecord`).

    ``capacities``: the static work capacities (:class:`~cusgs_jax.training.capacity.Capacities`,
    owned and grown by the caller; default: the config's first guesses). ``loss_terms``: research code's own
    terms (:class:`~cusgs_jax.training.loss_terms.LossTerm`), added to the loss with their weights from
    ``batch["loss_weights"]`` (:func:`loss_weights`). Every term's unweighted value is in the metrics
    (``loss_l1``, ``loss_ssim_loss``, ``loss_volume``, ``loss_feature``, ``loss_<name>``);
    :func:`~cusgs_jax.training.loss_terms.weighted_terms` weighs them on the host (they sum to ``metrics["loss"]``
    up to rounding). The weighing is not done in the program, where a product the loss also computes would
    change how XLA rounds the loss.

    With ``train.batch_size = B > 1`` every per-view entry has a leading view
    axis (``image`` [B, H, W, 3], ``camera.K`` [B, 3, 3], ``camera.world_to_camera``
    [B, 4, 4], ``index`` [B], ``features`` {model: [B, h, w, D]}; ``banks``, ``loss_weights``,
    ``seed_key`` and ``learning_rates`` shared), the views are sharded over a mesh and the step is placed on it
    (:func:`make_batched_step`). B = 1 runs the same body with one view and no mesh.

    **No truncated step.** When the view has more visible anchors than the
    static visible slots, more active Gaussians than G_act or more tile pairs than
    the pair capacity, the step changes nothing at all (not even ``state.step``)
    and reports the shortfall in ``metrics["dropped_anchors"]`` /
    ``["dropped_gaussians"]`` / ``["dropped_pairs"]``; the caller grows the
    capacities (:meth:`Capacities.grown`) and replays the same batch.
    """
    require_config(cfg, "make_train_step")
    capacities = Capacities.from_config(cfg) if capacities is None else capacities
    loss_terms = check_loss_terms(loss_terms)
    if cfg.train.batch_size > 1:
        return make_batched_step(cfg, tx, strategies, capacities, loss_terms)
    return jax.jit(_step_body(cfg, tx, strategies, capacities, mesh=None, loss_terms=loss_terms), donate_argnums=0)


def _step_body(cfg: Config, tx, strategies: tuple[Strategy, ...], capacities: Capacities, mesh, loss_terms=()):
    """``step(state, batch) -> (state, metrics)`` for B = ``train.batch_size`` views (not jitted).

    B = 1 (``mesh`` None): the batch has no view axis; the view's S anchor rows are updated
    row-sparsely (``optim.sparse``) or scattered into a dense gradient. B > 1: the views are
    rendered and differentiated on the devices of ``mesh`` (``shard_map``), their dense
    gradients averaged, and the update is dense. Everything after the per-view passes —
    finite check, completeness, statistics of every view in view order, metrics, update —
    is the same code for both.
    """
    from jax.sharding import PartitionSpec as P

    batch_size = cfg.train.batch_size
    sparse = cfg.optim.sparse and batch_size == 1

    def train_step(state: TrainState, batch):  # its name: the run's compile log counts jit(train_step)
        camera = batch["camera"]
        capacity = state.anchors.capacity
        one = _view_pass(cfg, capacities, capacity, loss_terms)
        seed_key = batch["seed_key"] if "seed_key" in batch else jax.random.PRNGKey(cfg.train.seed)
        key = jax.random.fold_in(seed_key, state.step)
        if batch_size == 1:
            loss, grads, parts = one(state.trainable, state.anchors, batch, key, state)
            latent_grads = [grads["anchor"].latent]
            views = [parts]
            reduce = lambda v, _: v  # noqa: E731
        else:
            def local_views(trainable, anchors, views, shared, keys, whole):
                """On one device: its B/D views' losses, parts and row gradients, and the dense gradient sum."""
                def visit(args):
                    view, view_key = args
                    loss, grads, parts = one(trainable, anchors, dict(view, **shared), view_key, whole)
                    return loss, grads, parts, _dense(grads, parts["view"], capacity)

                loss, grads, parts, dense = jax.lax.map(visit, (views, keys))
                total = jax.tree_util.tree_map(lambda g: jax.lax.psum(jnp.sum(g, axis=0), parallel.AXIS), dense)
                return loss, grads["anchor"].latent, parts, total

            sharded = jax.shard_map(local_views, mesh=mesh,
                                    in_specs=(P(), P(), P(parallel.AXIS), P(), P(parallel.AXIS), P()),
                                    out_specs=(P(parallel.AXIS),) * 3 + (P(),),
                                    check_vma=False)  # the splatter's scans carry values that vary over views
            keys = jax.vmap(lambda b: jax.random.fold_in(key, b))(jnp.arange(batch_size))
            per_view = {k: v for k, v in batch.items() if k not in parallel.SHARED_INPUTS}
            shared = {k: v for k, v in batch.items() if k in parallel.SHARED_INPUTS}
            losses_b, latent_grad, parts, total = sharded(state.trainable, state.anchors, per_view, shared, keys, state)
            loss = jnp.mean(losses_b)
            grads = jax.tree_util.tree_map(lambda g: g / batch_size, total)
            pick = lambda tree, b: jax.tree_util.tree_map(lambda x: x[b], tree)  # noqa: E731
            latent_grads = [latent_grad[b] for b in range(batch_size)]
            views = [pick(parts, b) for b in range(batch_size)]
            reduce = lambda v, fold: fold(v)  # noqa: E731
        finite = _all_finite(loss, grads)  # O(S) with the sparse update: the anchor gradients have S rows
        work = parts["work"]
        complete = ((jnp.all(work["dropped_anchors"] == 0) & jnp.all(work["dropped_gaussians"] == 0)
                     & jnp.all(work["dropped_pairs"] == 0)))
        apply = finite & complete
        densify = dict(state.densify)
        for view_parts, latent_grad in zip(views, latent_grads):  # every view's statistics, in view order
            record = _record(view_parts, latent_grad, capacity, camera, state.step, apply)
            densify = {s.name: s.accumulate(densify[s.name], record) for s in strategies}  # gated by record.finite
        metrics = _metrics(loss, finite, parts, reduce)
        rates = batch.get("learning_rates")  # None: the rates tx was built with, as constants
        if sparse:
            state = _apply_rows(state, tx, grads, parts["view"].slots, parts["view"].valid, apply, rates)
        elif batch_size == 1:  # optim.sparse=false: the S rows scattered into a dense [A] gradient
            state = _apply(state, tx, _dense(grads, parts["view"], capacity), apply, rates)
        else:
            state = _apply(state, tx, grads, apply, rates)
        return _finish(state, finite, complete, densify), metrics

    return train_step


def _all_finite(loss, grads) -> jax.Array:
    return jnp.isfinite(loss) & jnp.all(jnp.array([jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grads)]))


def _dense(grads, view, capacity: int):
    """The gradient with the anchor rows [S] scattered into the anchor capacity [A] (zero elsewhere)."""
    return dict(grads, anchor=jax.tree_util.tree_map(lambda g: to_slots(g, view, capacity), grads["anchor"]))


def _select(apply, new, old):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(apply, a, b), new, old)


def _apply(state: TrainState, tx, grads, apply, rates=None) -> TrainState:
    """Dense masked optax update: applied only when ``apply``; dead anchor slots never move. ``rates``: the
    batch's ``learning_rates`` (:func:`cusgs_jax.training.optim.rate_arguments`) or None."""
    trainable = state.trainable
    updates, new_opt = tx.update(grads, state.opt_state, trainable, learning_rates=rates)
    # dead anchor slots never move (their Adam moments may still be non-zero)
    alive = state.anchors.alive
    updates["anchor"] = jax.tree_util.tree_map(
        lambda u: jnp.where(alive.reshape((-1,) + (1,) * (u.ndim - 1)), u, 0.0), updates["anchor"])
    new_trainable = jax.tree_util.tree_map(lambda p, u: p + u, trainable, updates)
    return state.with_trainable(_select(apply, new_trainable, trainable)).replace(
        opt_state=_select(apply, new_opt, state.opt_state))


def _apply_rows(state: TrainState, tx, grads, slots, valid, apply, rates=None) -> TrainState:
    """Row-sparse optax update over the S visible slots (gsplat ``visible_adam`` / selective Adam).

    Every per-anchor leaf of the parameters and of the optimiser state (found by type,
    :func:`cusgs_jax.model.anchors.is_per_anchor`) is gathered at ``slots``, the optimiser
    runs on those rows and the networks, and the rows are written back — only the
    ``valid`` ones, and only when ``apply``. Adam is elementwise, so a seen row gets exactly
    the dense update; an unseen row keeps its parameters and moments (the dense update would
    decay its moments and keep moving it on momentum). Step counts advance as in the dense
    update. Cost O(S) per per-anchor leaf.

    Args:
      grads: {"anchor": AnchorParams [S, …], networks}; slots: [S] int32; valid: [S] bool.
      rates: the batch's ``learning_rates`` or None (as :func:`_apply`).
    """
    capacity = state.anchors.capacity
    trainable = state.trainable
    rows, opt_rows = map_rows(lambda x: x[slots], trainable), map_rows(lambda x: x[slots], state.opt_state)
    updates, new_opt_rows = tx.update(grads, opt_rows, rows, learning_rates=rates)
    new_rows = jax.tree_util.tree_map(lambda p, u: p + u, rows, updates)
    index = jnp.where(apply & valid, slots, capacity)  # out of range: dropped

    def put(full, new):
        def visit(full_node, new_node):
            if is_per_anchor(full_node):
                return jax.tree_util.tree_map(lambda f, n: f.at[index].set(n, mode="drop"), full_node, new_node)
            return jax.tree_util.tree_map(lambda f, n: jnp.where(apply, n, f), full_node, new_node)

        return jax.tree_util.tree_map(visit, full, new, is_leaf=is_per_anchor)

    return state.with_trainable(put(trainable, new_rows)).replace(opt_state=put(state.opt_state, new_opt_rows))


def _finish(state: TrainState, finite, complete, densify) -> TrainState:
    return state.replace(densify=densify, step=state.step + complete.astype(jnp.int32),
                         skipped=state.skipped + (complete & ~finite).astype(jnp.int32))


def make_batched_step(cfg: Config, tx, strategies: tuple[Strategy, ...], capacities: Capacities | None = None,
                      loss_terms=()):
    """The step on B = ``train.batch_size`` views, sharded over the views mesh (B > 1).

    ``step(state, batch)`` with the batch of :func:`make_train_step` (leading view axis B).
    Every view is rendered and differentiated on its own device (``shard_map`` over the
    ``"views"`` axis of :func:`cusgs_jax.training.parallel.view_mesh`, B/D views per device,
    one after another with ``lax.map``: one view's intermediates in memory at a time, and the
    same per-view program as on another device count — ``vmap`` measured further apart);
    the loss is the mean of the B view losses, its gradient the mean of theirs (each view's
    S anchor rows scattered into [A], then a ``psum`` over the mesh), applied once by the
    replicated optimiser — densely over the alive rows whatever ``optim.sparse`` says (the
    views see different slots). Each view's record — its own ∂L_b/∂μ_2D and ∂L_b/∂z, as a
    single-view step would see them — is added to the densification statistics in view
    order, so growing and pruning count every view (gsplat's strategies rescale the
    batch-mean gradient by the number of cameras for the same reason). The step is complete
    only when no view dropped work; the metrics report the worst view's shortfall. The
    view-b key is ``fold_in(key(step), b)``. The body is :func:`_step_body`'s, as for B = 1.

    Inputs are placed on the mesh before the jitted call (state replicated, views split), so
    arrays coming back from host-side growing and pruning never change the compiled step.
    """
    capacities = Capacities.from_config(cfg) if capacities is None else capacities
    mesh = parallel.view_mesh(cfg)
    jitted = jax.jit(_step_body(cfg, tx, strategies, capacities, mesh, check_loss_terms(loss_terms)),
                     donate_argnums=0)

    def placed_step(state: TrainState, batch):
        state, batch = parallel.place_step_inputs(mesh, state, batch)
        return jitted(state, batch)

    placed_step.jitted = jitted  # the jitted part (compiled ahead by app/ahead.py)
    placed_step.mesh = mesh
    # for an ahead-of-time compile (app/ahead.py): the jitted step's argument types, and the placement its call does
    placed_step.types = functools.partial(parallel.place_step_types, mesh)
    placed_step.place = functools.partial(parallel.place_step_inputs, mesh)
    return placed_step
