"""Early opacity culling for random starts (docs/formats.md#carving-random-starts).

A scene without points (Blender, nerfstudio without a PLY) starts from random points: most become anchors in
empty space, and every step decodes them until Scaffold-GS's first opacity prune, which runs only inside the
growing schedule (``grow.start``). :class:`EarlyCullStrategy` applies the same rule earlier — an anchor seen
in most steps of a window whose Gaussians stayed transparent (Scaffold-GS ``prune_anchor``: its mean
Σ_n max(opacity, 0) per visit below ``grow.min_opacity``) is removed — every ``grow.early_cull_every`` steps
until the schedule takes over. The shell then shrinks the anchor capacity to what is alive
(:func:`cusgs_jax.densify.ops.shrunk_capacity`), so a step pays for the survivors.

``grow.early_cull=auto`` runs it for the random starts that carving could not carve by coverage
(:func:`resolve_early_cull`: no view with alpha, or ``data.carve=none``); a run from SfM points keeps its
strategies, its state and its numbers, and so does a carved Blender capture, where it removed next to nothing
(experiments/README.md#early-culling-of-random-starts).

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets per anchor, S gathered slots of a view.
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import Config, GrowConfig
from cusgs_jax.densify.base import Strategy, UpdateInfo
from cusgs_jax.model.anchors import PerAnchor

__all__ = ["CullStats", "EarlyCullStrategy", "resolve_early_cull"]

log = logging.getLogger("cusgs_jax")

SEASONED_SHARE = 0.8  # an anchor is judged once seen in this share of a window's steps (Scaffold-GS: 0.8)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CullStats(PerAnchor):
    """Per-anchor sums over the current window.

    Attributes:
      opacity_accum: [A] Σ over visits of Σ_n max(opacity, 0).
      visits: [A] steps in which the anchor was decoded.
    """

    opacity_accum: jax.Array
    visits: jax.Array

    @staticmethod
    def zeros(capacity: int) -> CullStats:
        return CullStats(jnp.zeros(capacity), jnp.zeros(capacity))


class EarlyCullStrategy(Strategy):
    """Opacity culling every ``grow.early_cull_every`` steps before ``grow.start`` (module doc).

    State: :class:`CullStats`, accumulated in the jitted step from step 0 and reset after each pass.
    """

    name = "early_cull"

    def __init__(self, cfg: GrowConfig):
        self.cfg = cfg

    def init_state(self, capacity: int) -> CullStats:
        return CullStats.zeros(capacity)

    def accumulate(self, stats: CullStats, view) -> CullStats:
        """Inside the step: the decoded anchors' visits and opacities (S gathered slots), before ``grow.start``."""
        capacity = stats.visits.shape[0]
        on = view.slots.valid & (view.step < self.cfg.start) & view.finite
        index = jnp.where(on, view.slots.slots, capacity)  # out of range: dropped
        opacity = jnp.sum(jnp.maximum(view.gaussians.opacities.reshape(on.shape[0], -1), 0.0), axis=-1)
        # jnp.where, not a product with 0: a skipped step's non-finite values add exactly 0
        return CullStats(opacity_accum=stats.opacity_accum.at[index].add(jnp.where(on, opacity, 0.0), mode="drop"),
                         visits=stats.visits.at[index].add(on.astype(jnp.float32), mode="drop"))

    def due(self, step: int) -> bool:
        """A pass after ``step`` completed steps: every ``grow.early_cull_every`` steps before ``grow.start``."""
        every = self.cfg.early_cull_every
        return 0 < step < self.cfg.start and step % every == 0

    def only_removes(self, step: int) -> bool:
        """An early cull only clears ``alive`` bits."""
        del step
        return True

    def update(self, state, tx, step: int) -> tuple[object, UpdateInfo]:
        """Remove the seasoned transparent anchors, then start a new window (host side).

        Returns:
          (state, :class:`~cusgs_jax.densify.base.UpdateInfo`): ``pruned`` anchors; ``extra`` ``alive`` (after
          the pass) and ``judged`` (anchors seen often enough to be judged).
        """
        del tx
        stats = state.densify[self.name]
        alive = np.asarray(state.anchors.alive)
        visits, opacity = np.asarray(stats.visits), np.asarray(stats.opacity_accum)
        judged = alive & (visits >= SEASONED_SHARE * self.cfg.early_cull_every)
        prune = judged & (opacity < self.cfg.min_opacity * visits)
        anchors = state.anchors.replace(alive=jax.device_put(alive & ~prune))
        fresh = CullStats(*(jax.device_put(np.zeros(alive.shape[0], np.float32)) for _ in range(2)))
        state = state.replace(anchors=anchors, densify={**state.densify, self.name: fresh})
        return state, UpdateInfo(pruned=int(prune.sum()), extra=dict(alive=int((alive & ~prune).sum()),
                                                                    judged=int(judged.sum())))


def resolve_early_cull(cfg: Config, random_start: bool, carved_by_coverage: bool = False) -> Config:
    """``cfg`` with ``grow.early_cull=auto`` replaced: ``on`` for a random start (a layout without points) that
    carving did not carve by the views' coverage (``carved_by_coverage``: some training view had alpha), else
    ``off``. A set value is kept."""
    if cfg.grow.early_cull != "auto":
        return cfg
    return cfg.replace(grow=dict(early_cull="on" if random_start and not carved_by_coverage else "off"))
