"""Resizing the training state in one place: anchors, optimiser moments and statistics together.

In the spirit of gsplat's ``strategy/ops.py``: whatever a strategy does to the
anchor slots (grow or shrink the capacity, restart refilled slots) is done to every
per-anchor array at once — the :class:`~cusgs_jax.model.anchors.AnchorState`,
the matching Adam moments (located with ``optax.tree_utils.tree_map_params``)
and every strategy's statistics. Which arrays are per-anchor is declared by
type (:class:`~cusgs_jax.model.anchors.PerAnchor`), never guessed from shapes.

``state`` is any frozen dataclass with ``anchors``, ``opt_state`` and
``densify`` fields and a ``replace`` method (:class:`cusgs_jax.training.state.TrainState`).
Host side, between steps; each resize is one jitted program per capacity (``tx`` and the capacity static),
not one small program per array shape. They move and zero rows, never compute: the values are the same
either way.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
import optax

from cusgs_jax.model.anchors import capacity_rung, is_per_anchor, map_rows, pad_leaf, pad_rows, zero_leaf, zero_rows

SHRINK_BELOW = 0.25
"""The capacity shrinks when the alive anchors fill less than this fraction of it (:func:`shrunk_capacity`)."""
SHRINK_HEADROOM = 2.0
"""A shrunk capacity holds this many times the alive anchors (room to grow before it must grow again)."""
CAPACITY_MULTIPLE = 256
"""Shrunk capacities off the capacity ladder are multiples of this (few distinct shapes, few compiles)."""


def map_moments(tx: optax.GradientTransformation, fn, opt_state):
    """Apply ``fn`` to every per-anchor array of the optimiser state that mirrors the parameters."""
    return optax.tree_utils.tree_map_params(
        tx, lambda node: map_rows(fn, node) if is_per_anchor(node) else node, opt_state, is_leaf=is_per_anchor)


@functools.partial(jax.jit, static_argnums=(1, 2))
def grow_capacity(state, tx, new_capacity: int):
    """Pad every per-anchor array of ``state`` to ``new_capacity`` slots (new slots dead and zero)."""
    return state.replace(anchors=pad_rows(state.anchors, new_capacity),
                         densify=pad_rows(state.densify, new_capacity),
                         opt_state=map_moments(tx, lambda x: pad_leaf(x, new_capacity), state.opt_state))


def resize_capacity(state, tx, new_capacity: int, keep=None):
    """Move the rows ``keep`` (default: the alive slots, in slot order) of every per-anchor array of
    ``state`` — anchors, Adam moments, statistics — to the front of a capacity of ``new_capacity``
    slots; the rest are dead and zero. With the default ``keep`` the step on the result gives every
    alive anchor the same loss, gradient and update as on ``state`` (dead slots contribute nothing).

    Args:
      keep: [K] int slot indices, K ≤ ``new_capacity``; None: the alive slots.
    """
    keep = np.flatnonzero(np.asarray(state.anchors.alive)) if keep is None else np.asarray(keep)
    if len(keep) > new_capacity:
        raise ValueError(f"cannot keep {len(keep)} anchor rows in a capacity of {new_capacity}")
    return _moved(state, tx, keep, new_capacity)


@functools.partial(jax.jit, static_argnums=(1, 3))
def _moved(state, tx, keep, new_capacity: int):
    """:func:`resize_capacity` of the rows ``keep`` [K] int."""
    def leaf(x):
        return pad_leaf(x[keep], new_capacity)

    return state.replace(anchors=map_rows(leaf, state.anchors), densify=map_rows(leaf, state.densify),
                         opt_state=map_moments(tx, leaf, state.opt_state))


def shrunk_capacity(alive: int, capacity: int, ladder: bool = False) -> int | None:
    """The smaller anchor capacity a state should move to, or None to keep ``capacity``.

    Pruning can leave a capacity sized for the initial points nearly empty (100k random initial
    points pruned to a few thousand anchors), and every step pays for the capacity's slots
    (visible-slot, active and pair capacities are fractions of it; the statistics are [A]).
    Shrink when fewer than :data:`SHRINK_BELOW` of the slots are alive, to :data:`SHRINK_HEADROOM` × alive
    rounded up to :data:`CAPACITY_MULTIPLE` — with ``ladder`` (``model.capacity_ladder``), to its rung
    (:func:`~cusgs_jax.model.anchors.capacity_rung`).
    """
    if alive >= SHRINK_BELOW * capacity:
        return None
    if ladder:
        target = capacity_rung(int(np.ceil(max(alive, 1) * SHRINK_HEADROOM)))
    else:
        target = int(np.ceil(max(alive, 1) * SHRINK_HEADROOM / CAPACITY_MULTIPLE) * CAPACITY_MULTIPLE)
    return target if target < capacity else None


@functools.partial(jax.jit, static_argnums=(1,))
def restart_rows(state, tx, rows):
    """Slots ``rows`` [A] bool hold new anchors: zero their optimiser moments and every statistic."""
    return state.replace(densify=zero_rows(state.densify, rows),
                         opt_state=map_moments(tx, lambda x: zero_leaf(x, rows), state.opt_state))
