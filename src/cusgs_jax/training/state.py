"""The training state: anchors, networks, optimiser state and densification statistics.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, V training views, E appearance size.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cusgs_jax.config import Config, require
from cusgs_jax.densify.base import Strategy
from cusgs_jax.model.anchors import AnchorState, anchor_layout, anchors_of_layout, auto_voxel_size
from cusgs_jax.model.decode import init_decoder
from cusgs_jax.model.field import init_memory_heads
from cusgs_jax.model.queries import init_query_heads
from cusgs_jax.training.optim import make_optimizer

log = logging.getLogger("cusgs_jax")
MIN_ANCHORS = 4  # fewer cannot represent a scene: refused
FEW_ANCHORS = 64  # fewer is allowed but warned about


def _check_scaffold(count: int, voxel_size: float, points: np.ndarray) -> None:
    """Refuse a scaffold of ``count`` anchors too coarse to mean anything; warn when it is merely coarse.

    The hint names the cause the numbers show: points at one location; nearly one anchor per distinct point
    (too few initial points, whatever the cell: a random start that carving left almost empty, or a sparse
    reconstruction — a smaller cell cannot help); or many points per anchor (the cell is too large: a smaller
    one, or ``model.voxel_size=auto`` unless the cell already is the points' auto spacing)."""
    distinct = len(np.unique(np.asarray(points, np.float64), axis=0))
    if distinct < 2:
        hint = (f"the {len(points)} points lie at {distinct} location(s): check the initial points (a reconstruction's "
                "points3D, or what carving left of a random start)")
    elif 2 * count >= distinct:
        hint = ("there are too few initial points, not too large a cell (about one point per anchor): a random start "
                "(a layout without points) keeps what carving by the training views leaves — see the 'carved the "
                "random initial points' log line and eval.json's carving (data.carve=none keeps every point, "
                "data.random_points draws more); from a reconstruction, its points (points3D) are too sparse")
    else:
        auto = auto_voxel_size(points)
        hint = (f"model.voxel_size is already these points' auto spacing ({auto:.4g}): the points are too few or too "
                "clustered; check them" if math.isclose(voxel_size, auto, rel_tol=1e-6) else
                f"use model.voxel_size=auto (here {auto:.4g}) or a smaller cell")
    require(count >= MIN_ANCHORS, "model.voxel_size", voxel_size,
            f"leaves only {count} anchor(s) for {len(points)} initial points (the cell is about as large as the "
            "scene, whose extent is 1 in these units)" if 2 * count < distinct else
            f"leaves only {count} anchor(s) for {len(points)} initial points", hint)
    if count < FEW_ANCHORS:
        log.warning("only %d anchors from %d initial points at model.voxel_size=%g: the model will be very coarse; %s",
                    count, len(points), voxel_size, hint)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """Everything that changes during training (a pytree; checkpointed whole).

    Attributes:
      anchors: :class:`AnchorState`, every per-anchor array (centres, alive, learnable arrays).
      nets: shared networks {"decoder", "appearance"?: [V, E], "queries"?: query heads,
        "memory"?: {model: attention head}}; only what the configuration uses exists.
      opt_state: optax state over :attr:`trainable`.
      densify: {strategy name: its per-anchor statistics}.
      step: [] int32 completed steps.
      skipped: [] int32 updates skipped because loss or gradient was not finite.
    """

    anchors: AnchorState
    nets: dict
    opt_state: Any
    densify: dict
    step: jax.Array
    skipped: jax.Array

    @property
    def trainable(self) -> dict:
        """The tree the optimiser updates: {"anchor": AnchorParams, **nets}."""
        return {"anchor": self.anchors.params, **self.nets}

    def with_trainable(self, trainable: dict) -> TrainState:
        nets = {k: v for k, v in trainable.items() if k != "anchor"}
        return self.replace(anchors=self.anchors.replace(params=trainable["anchor"]), nets=nets)

    def replace(self, **changes) -> TrainState:
        return dataclasses.replace(self, **changes)


def init_nets(key, cfg: Config, num_train_views: int, banks: dict | None = None) -> dict:
    """Network parameters; the feature heads exist only when feature models are configured.

    One program for every network's draws (:func:`_draw_nets`), bit for bit the values the draws give
    one call at a time (``tests/training/test_state.py``); ``banks`` give only their shapes.
    """
    if cfg.features.enabled and (banks is None or set(banks) != {m.name for m in cfg.features.model_list}):
        raise ValueError("feature models are configured: pass one PSC bank per model")
    bank_shapes = tuple(sorted((name, np.shape(bank)) for name, bank in (banks or {}).items()))
    return _draw_nets(key, cfg, num_train_views, bank_shapes if cfg.features.enabled else None)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _draw_nets(key, cfg: Config, num_train_views: int, banks) -> dict:
    """:func:`init_nets` (``banks``: ((model, (M, D)), …), static, or None)."""
    model, features = cfg.model, cfg.features
    banks = {name: jax.ShapeDtypeStruct(shape, jnp.float32) for name, shape in banks or ()}
    nets = {"decoder": init_decoder(key, model.decoder())}
    if model.appearance:
        # Scaffold-GS: nn.Embedding default init N(0, 1).
        nets["appearance"] = jax.random.normal(jax.random.fold_in(key, 1), (num_train_views, model.appearance_dim))
    if features.enabled:
        if model.query_granularity == "per_anchor":
            nets["queries"] = init_query_heads(jax.random.fold_in(key, 2), features, model.latent_dim,
                                               model.appearance_dim if model.appearance else 0)
        nets["memory"] = init_memory_heads(jax.random.fold_in(key, 3), features, banks)
    return nets


def init_train_state(cfg: Config, points: np.ndarray, num_train_views: int, extent: float,
                     strategies: tuple[Strategy, ...], banks: dict | None = None
                     ) -> tuple[TrainState, optax.GradientTransformation]:
    """Fresh state and optimiser from an SfM point cloud.

    Args:
      points: [P, 3] SfM points (in the normalised frame of :mod:`cusgs_jax.data.normalize`).
      extent: scene extent (scales the offsets' learning rate; 1 in the normalised frame).
      strategies: the densification strategies (:func:`cusgs_jax.densify.factory.make_strategies`).
      banks: {model: [M, D] PSC entries} when feature models are configured.
    Returns:
      (TrainState, optax transformation).
    """
    model = cfg.model
    require(model.voxel_size is not None, "model.voxel_size", "auto",
            "is resolved from the points first",
            "call cusgs_jax.app.resolve.resolve_voxel_size(cfg, points)")
    table = cfg.features.enabled and model.query_granularity == "per_gaussian"
    layout = anchor_layout(points, model.voxel_size, capacity_factor=model.capacity_factor,
                           ladder=model.capacity_ladder)
    _check_scaffold(int(layout["alive"].sum()), model.voxel_size, points)

    key = jax.random.PRNGKey(cfg.train.seed)
    nets = init_nets(key, cfg, num_train_views, banks)

    def fresh(layout, nets):
        """Everything but the optimiser state (traceable)."""
        anchors = anchors_of_layout(layout, n_offsets=model.n_offsets, latent_dim=model.latent_dim,
                                    query_dim=cfg.features.query_dim if table else 0, key=jax.random.fold_in(key, 2))
        return TrainState(anchors=anchors, nets=nets, opt_state=None,
                          densify={s.name: s.init_state(anchors.capacity) for s in strategies},
                          step=jnp.int32(0), skipped=jnp.int32(0))

    # the optimiser is built from the tree's structure, then anchors, statistics and optimiser state in one program
    # (zeros and the host's layout: one compile, not one per array)
    tx = make_optimizer(cfg.optim, jax.eval_shape(fresh, layout, nets).trainable, cfg.train.iterations, extent,
                        cfg.train.batch_size)

    @jax.jit
    def init_state(layout, nets):
        state = fresh(layout, nets)
        return state.replace(opt_state=tx.init(state.trainable))

    return init_state(layout, nets), tx
