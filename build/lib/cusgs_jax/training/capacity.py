"""Work capacities that must never drop work: visible-anchor slots and tile–Gaussian pairs.

A jitted step has static shapes, so two amounts of per-view work have a fixed
capacity: the S visible slots the frustum gather decodes
(``model.visible_fraction`` of the anchor capacity A) and the tile–Gaussian
pairs the splatter sorts (``splat.max_pairs_per_gaussian`` per decoded
Gaussian). Both only set the *first* capacity. As in jax-md's neighbour lists,
the step reports what did not fit (``dropped_anchors``, ``dropped_pairs``) and
then changes nothing; the host grows the capacity to a bucketed size (so a
run recompiles a handful of times at most), rebuilds the step and replays it
(:func:`grow_for`). Evaluation renders do the same (:class:`ExactRender`).
No update or metric is ever computed from a truncated set.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable

from cusgs_jax.config import Config

log = logging.getLogger("cusgs_jax")

PAIR_SLACK = 4096  # pairs added to ``max_pairs_per_gaussian · G`` (covers tiny scenes)
FRACTION_BUCKET = 8  # visible_fraction grows in steps of 1/8


def max_pairs(pairs_per_gaussian: float, num_gaussians: int) -> int:
    """Static tile–Gaussian pair capacity for G = ``num_gaussians`` decoded Gaussians."""
    return int(pairs_per_gaussian * num_gaussians) + PAIR_SLACK


def grown_pairs_per_gaussian(current: float, needed_pairs: int, num_gaussians: int) -> float:
    """A pair capacity that holds ``needed_pairs``: ≥ 1.5× the current, 25 % headroom, in steps of 0.5."""
    want = max(1.5 * current, 1.25 * (needed_pairs - PAIR_SLACK) / max(num_gaussians, 1))
    return math.ceil(want * 2.0) / 2.0


def grown_visible_fraction(current: float, needed_slots: int, capacity: int) -> float:
    """A visible fraction of the A = ``capacity`` slots that holds ``needed_slots`` with 10 % headroom.

    Grows by at least one bucket of 1/8 and never beyond 1 (every slot decoded).
    """
    want = max(current + 1.0 / FRACTION_BUCKET, 1.1 * needed_slots / max(capacity, 1))
    return min(1.0, math.ceil(want * FRACTION_BUCKET) / FRACTION_BUCKET)


def grow_for(cfg: Config, metrics: dict, capacity: int, num_gaussians: int) -> Config:
    """The configuration whose capacities fit the work a step reported as dropped.

    Args:
      metrics: host values of the step's ``visible_anchors``, ``dropped_anchors``,
        ``pairs`` and ``dropped_pairs``.
      capacity: anchor capacity A; num_gaussians: G = S·N decoded by that step.
    Returns:
      ``cfg`` with ``model.visible_fraction`` grown when anchors were dropped
      (the replay then measures the pairs anew), else with
      ``splat.max_pairs_per_gaussian`` grown when pairs were dropped.
    """
    if metrics["dropped_anchors"] > 0:
        needed = int(metrics["visible_anchors"]) + int(metrics["dropped_anchors"])
        fraction = grown_visible_fraction(cfg.model.visible_fraction, needed, capacity)
        log.info("a view sees %d anchors, more than %d visible slots: model.visible_fraction %.3g -> %.3g "
                 "(the step recompiles and replays)", needed, int(metrics["visible_anchors"]),
                 cfg.model.visible_fraction, fraction)
        return cfg.replace(model=dict(visible_fraction=fraction))
    if metrics["dropped_pairs"] > 0:
        needed = int(metrics["pairs"]) + int(metrics["dropped_pairs"])
        pairs = grown_pairs_per_gaussian(cfg.splat.max_pairs_per_gaussian, needed, num_gaussians)
        log.info("a view needs %d tile pairs, more than %d: splat.max_pairs_per_gaussian %.3g -> %.3g "
                 "(recompiles and replays)", needed, int(metrics["pairs"]), cfg.splat.max_pairs_per_gaussian, pairs)
        return cfg.replace(splat=dict(max_pairs_per_gaussian=pairs))
    return cfg


def capacities(cfg: Config) -> dict:
    """The grown capacities, as checkpoint metadata and ``eval.json`` record them."""
    return dict(visible_fraction=cfg.model.visible_fraction, max_pairs_per_gaussian=cfg.splat.max_pairs_per_gaussian)


def with_capacities(cfg: Config, saved: dict | None) -> Config:
    """``cfg`` with capacities restored from checkpoint metadata (never smaller than configured)."""
    if not saved:
        return cfg
    return cfg.replace(
        model=dict(visible_fraction=max(cfg.model.visible_fraction, float(saved["visible_fraction"]))),
        splat=dict(max_pairs_per_gaussian=max(cfg.splat.max_pairs_per_gaussian,
                                              float(saved["max_pairs_per_gaussian"]))))


@dataclasses.dataclass
class ExactRender:
    """A jitted render that never returns a truncated image.

    ``build(cfg)`` returns a jitted ``fn(anchors, ...) -> (*outputs, dropped_pairs, pairs)``
    rendering every slot of ``anchors`` (G = A·N Gaussians). Calling this object
    returns ``outputs`` (a tuple); when pairs were dropped it grows
    ``splat.max_pairs_per_gaussian``, rebuilds and renders again (``growths`` counts it).
    """

    build: Callable[[Config], Callable]
    cfg: Config
    growths: int = 0
    fn: Callable | None = None

    def __call__(self, anchors, *args):
        while True:
            if self.fn is None:
                self.fn = self.build(self.cfg)
            *outputs, dropped, pairs = self.fn(anchors, *args)
            if int(dropped) == 0:
                return tuple(outputs)
            metrics = dict(dropped_anchors=0, dropped_pairs=int(dropped), pairs=int(pairs))
            self.cfg = grow_for(self.cfg, metrics, anchors.capacity, anchors.capacity * self.cfg.model.n_offsets)
            self.fn, self.growths = None, self.growths + 1
