"""Resizing the training state in one place: anchors, optimiser moments and statistics together.

In the spirit of gsplat's ``strategy/ops.py``: whatever a strategy does to the
anchor slots (grow the capacity, restart refilled slots) is done to every
per-anchor array at once — the :class:`~cusgs_jax.model.anchors.AnchorState`,
the matching Adam moments (located with ``optax.tree_utils.tree_map_params``)
and every strategy's statistics. Which arrays are per-anchor is declared by
type (:class:`~cusgs_jax.model.anchors.PerAnchor`), never guessed from shapes.

``state`` is any frozen dataclass with ``anchors``, ``opt_state`` and
``densify`` fields and a ``replace`` method (:class:`cusgs_jax.training.state.TrainState`).
Host side, between steps.
"""

from __future__ import annotations

import optax

from cusgs_jax.model.anchors import is_per_anchor, map_rows, pad_leaf, pad_rows, zero_leaf, zero_rows


def map_moments(tx: optax.GradientTransformation, fn, opt_state):
    """Apply ``fn`` to every per-anchor array of the optimiser state that mirrors the parameters."""
    return optax.tree_utils.tree_map_params(
        tx, lambda node: map_rows(fn, node) if is_per_anchor(node) else node, opt_state, is_leaf=is_per_anchor)


def grow_capacity(state, tx, new_capacity: int):
    """Pad every per-anchor array of ``state`` to ``new_capacity`` slots (new slots dead and zero)."""
    return state.replace(anchors=pad_rows(state.anchors, new_capacity),
                         densify=pad_rows(state.densify, new_capacity),
                         opt_state=map_moments(tx, lambda x: pad_leaf(x, new_capacity), state.opt_state))


def restart_rows(state, tx, rows):
    """Slots ``rows`` [A] bool hold new anchors: zero their optimiser moments and every statistic."""
    return state.replace(densify=zero_rows(state.densify, rows),
                         opt_state=map_moments(tx, lambda x: zero_leaf(x, rows), state.opt_state))
