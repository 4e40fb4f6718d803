"""Work capacities that must never drop work: visible-anchor slots, active Gaussians and tile pairs.

A jitted step has static shapes, so three amounts of per-view work have a fixed
capacity, held by one :class:`Capacities` value that the shell owns, passes to
``make_train_step`` and to every renderer, checkpoints and grows:

* the S visible slots the frustum gather decodes (``visible_fraction`` of the
  anchor capacity A);
* the G_act active Gaussians — those that pass Scaffold's opacity mask — that
  reach the splatter (``active_fraction`` of the S·N decoded ones,
  :mod:`cusgs_jax.model.active`);
* the tile–Gaussian pairs the splatter sorts (``pairs_per_active`` per active
  Gaussian, so it follows the compaction).

The user's config (``model.visible_fraction``, ``splat.active_fraction``,
``splat.max_pairs_per_gaussian``) only gives the *first* guesses
(:meth:`Capacities.from_config`). As in jax-md's neighbour lists, the step
reports what did not fit (``dropped_anchors``, ``dropped_gaussians``,
``dropped_pairs``) and then changes nothing; the shell grows the capacity to a
bucketed size (so a run recompiles a handful of times at most), rebuilds the
step and replays it (:meth:`Capacities.grown`). Evaluation renders do the same
(:class:`ExactRender`). No update or metric is ever computed from a truncated set.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable

import jax

from cusgs_jax.config import Config
from cusgs_jax.model.decode import num_visible_slots

log = logging.getLogger("cusgs_jax")

PAIR_SLACK = 4096  # pairs added to ``max_pairs_per_gaussian · G`` (covers tiny scenes)
FRACTION_BUCKET = 8  # visible_fraction grows in steps of 1/8
ACTIVE_BUCKET = 16  # active_fraction grows in steps of 1/16
# Headroom over the need after an overflow: a growing model overflows again soon, and every growth
# recompiles the whole step (~30 s for the demo's feature step on 2 CPU cores) while 25 % more slots
# cost a few per cent of a step; the first fit (Capacities.fitted) uses the tighter 1.1 / 1.15.
GROWTH_HEADROOM = 1.25
FIT_HEADROOM = 1.1  # the least headroom a first fit leaves (its visible slots; Capacities.fitted)
WORK_KEYS = ("visible_anchors", "active_gaussians", "pairs")  # a view's work, as training/render.view_work measures it
EVAL_HEADROOM = 1.5  # visible slots of an evaluation render over the step's (Capacities.for_evaluation)


def growth_fill(alive: int, anchor_capacity: int) -> float:
    """The growth of a view's work a run forecasts when its strategies grow the ``alive`` anchors into all
    ``anchor_capacity`` slots: A / alive (a view sees anchors in proportion to the alive ones), at least 1."""
    return max(1.0, anchor_capacity / max(int(alive), 1))


def max_pairs(pairs_per_gaussian: float, num_gaussians: int) -> int:
    """Static tile–Gaussian pair capacity for G = ``num_gaussians`` decoded Gaussians."""
    return max(1, int(pairs_per_gaussian * num_gaussians) + PAIR_SLACK)


def grown_pairs_per_gaussian(current: float, needed_pairs: int, num_gaussians: int) -> float:
    """A pair capacity that holds ``needed_pairs``: ≥ 1.5× the current, 25 % headroom, in steps of 0.5."""
    want = max(1.5 * current, 1.25 * (needed_pairs - PAIR_SLACK) / max(num_gaussians, 1))
    return math.ceil(want * 2.0) / 2.0


def grown_visible_fraction(current: float, needed_slots: int, capacity: int,
                           headroom: float = GROWTH_HEADROOM) -> float:
    """A visible fraction of the A = ``capacity`` slots that holds ``headroom`` × ``needed_slots``.

    Grows by at least one bucket of 1/8 and never beyond 1 (every slot decoded).
    """
    want = max(current + 1.0 / FRACTION_BUCKET, headroom * needed_slots / max(capacity, 1))
    return min(1.0, math.ceil(want * FRACTION_BUCKET) / FRACTION_BUCKET)


def grown_active_fraction(current: float, needed: int, decoded: int, headroom: float = GROWTH_HEADROOM) -> float:
    """An active fraction of the ``decoded`` = S·N Gaussians that holds ``headroom`` × ``needed``.

    Grows by at least one bucket of 1/16 and never beyond 1 (every decoded Gaussian).
    """
    want = max(current + 1.0 / ACTIVE_BUCKET, headroom * needed / max(decoded, 1))
    return min(1.0, math.ceil(want * ACTIVE_BUCKET) / ACTIVE_BUCKET)


@dataclasses.dataclass(frozen=True)
class Capacities:
    """The static work capacities of a step or render (hashable; closed over, never traced).

    Attributes:
      visible_fraction: S = ceil(f · A) visible slots are decoded per view.
      active_fraction: G_act = ceil(f · S·N) active Gaussians are rasterised per view.
      pairs_per_active: P = ceil(p · G_act) + ``PAIR_SLACK`` tile–Gaussian pairs.
    """

    visible_fraction: float
    active_fraction: float
    pairs_per_active: float

    @classmethod
    def from_config(cls, cfg: Config) -> Capacities:
        """The user's first guesses (``model.visible_fraction``, ``splat.active_fraction``,
        ``splat.max_pairs_per_gaussian``)."""
        return cls(float(cfg.model.visible_fraction), float(cfg.splat.active_fraction),
                   float(cfg.splat.max_pairs_per_gaussian))

    def visible_slots(self, anchor_capacity: int) -> int:
        """S for an anchor capacity A."""
        return num_visible_slots(anchor_capacity, self.visible_fraction)

    def active_gaussians(self, anchor_capacity: int, n_offsets: int) -> int:
        """G_act for an anchor capacity A and N offsets, at least 1 and at most S·N."""
        decoded = self.visible_slots(anchor_capacity) * n_offsets
        return max(1, min(decoded, int(-(-self.active_fraction * decoded // 1))))

    def pairs(self, anchor_capacity: int, n_offsets: int) -> int:
        """P for an anchor capacity A and N offsets."""
        return max_pairs(self.pairs_per_active, self.active_gaussians(anchor_capacity, n_offsets))

    def grown(self, metrics: dict, anchor_capacity: int, n_offsets: int, announce: bool = True) -> Capacities:
        """The capacities that fit the work a step or render reported as dropped.

        Args:
          metrics: host values of ``visible_anchors``, ``dropped_anchors``, ``active_gaussians``,
            ``dropped_gaussians``, ``pairs`` and ``dropped_pairs``.
          anchor_capacity: A of that step; n_offsets: N.
          announce: log the growth (False for a forecast, :meth:`replayed`).
        Returns:
          ``self`` with the first capacity that overflowed grown, in the order the work is done
          (slots, then active Gaussians, then pairs: the replay measures the later ones anew).
        """
        if metrics.get("dropped_anchors", 0) > 0:
            needed = int(metrics["visible_anchors"]) + int(metrics["dropped_anchors"])
            fraction = grown_visible_fraction(self.visible_fraction, needed, anchor_capacity)
            (log.info if announce else log.debug)("a view sees %d anchors, more than %d visible slots: visible fraction %.3g -> %.3g "
                     "(the step recompiles and replays)", needed, int(metrics["visible_anchors"]),
                     self.visible_fraction, fraction)
            return dataclasses.replace(self, visible_fraction=fraction)
        if metrics.get("dropped_gaussians", 0) > 0:
            needed = int(metrics["active_gaussians"]) + int(metrics["dropped_gaussians"])
            decoded = self.visible_slots(anchor_capacity) * n_offsets
            fraction = grown_active_fraction(self.active_fraction, needed, decoded)
            (log.info if announce else log.debug)("a view has %d active Gaussians, more than %d: active fraction %.3g -> %.3g "
                     "(recompiles and replays)", needed, self.active_gaussians(anchor_capacity, n_offsets),
                     self.active_fraction, fraction)
            return dataclasses.replace(self, active_fraction=fraction)
        if metrics.get("dropped_pairs", 0) > 0:
            needed = int(metrics["pairs"]) + int(metrics["dropped_pairs"])
            pairs = grown_pairs_per_gaussian(self.pairs_per_active, needed,
                                             self.active_gaussians(anchor_capacity, n_offsets))
            (log.info if announce else log.debug)("a view needs %d tile pairs, more than %d: pairs per active Gaussian %.3g -> %.3g "
                     "(recompiles and replays)", needed, int(metrics["pairs"]), self.pairs_per_active, pairs)
            return dataclasses.replace(self, pairs_per_active=pairs)
        return self

    def shortfall(self, need: dict, anchor_capacity: int, n_offsets: int) -> dict | None:
        """The metrics a step with these capacities reports for a view that needs ``need``
        (:func:`cusgs_jax.training.render.view_work`) — its first overflowing capacity, as :meth:`grown`
        reads it — or None when the view fits."""
        slots = self.visible_slots(anchor_capacity)
        if need["visible_anchors"] > slots:
            return dict(visible_anchors=slots, dropped_anchors=need["visible_anchors"] - slots)
        active = self.active_gaussians(anchor_capacity, n_offsets)
        if need["active_gaussians"] > active:
            return dict(active_gaussians=active, dropped_gaussians=need["active_gaussians"] - active)
        pairs = self.pairs(anchor_capacity, n_offsets)
        if need["pairs"] > pairs:
            return dict(pairs=pairs, dropped_pairs=need["pairs"] - pairs)
        return None

    def roomy(self, needs: list[dict], anchor_capacity: int, n_offsets: int,
              headroom: float = GROWTH_HEADROOM) -> bool:
        """Whether every view of ``needs`` (:func:`cusgs_jax.training.render.view_work`) fits these capacities
        ``headroom`` times over: visible slots, active Gaussians and tile pairs."""
        return all(self.shortfall({key: headroom * need[key] for key in WORK_KEYS}, anchor_capacity, n_offsets)
                   is None for need in needs)

    def replayed(self, needs: list[dict], anchor_capacity: int, n_offsets: int) -> list[Capacities]:
        """The capacities a run starting from these would pass through on steps whose views need ``needs``,
        in order (each overflow grown by :meth:`grown` and replayed): what a compile ahead prepares."""
        passed, current = [], self
        for need in needs:
            while (short := current.shortfall(need, anchor_capacity, n_offsets)) is not None:
                grown = current.grown(short, anchor_capacity, n_offsets, announce=False)
                if grown == current:
                    break
                current = grown
                passed.append(current)
        return passed

    @classmethod
    def fitted(cls, needs: dict, anchor_capacity: int, n_offsets: int, fill: float = 1.0) -> Capacities:
        """Capacities sized by measured need with headroom (the shell's start; jax-md sizes a
        neighbour list from the first positions the same way).

        Args:
          needs: the most any probed view needed: ``visible_anchors``, ``active_gaussians``, ``pairs``
            (:func:`cusgs_jax.training.render.view_work`).
          fill: the growth of the need the run forecasts (≥ 1): every need is scaled by it before the headroom —
            :func:`growth_fill` where a strategy will grow the alive anchors into the capacity (a view then sees
            about ``fill`` times the anchors it sees now), 1 for a fit to what the views need now.
        Returns:
          visible slots ≥ 1.1 × the visible anchors (in buckets of 1/8 of A), active Gaussians
          ≥ 1.15 × the active ones (buckets of 1/16 of S·N), pairs ≥ 1.25 × the pairs (steps of 0.5
          per active Gaussian).
        """
        fill = max(1.0, float(fill))
        needs = {key: math.ceil(fill * int(needs[key])) for key in WORK_KEYS} if fill > 1.0 else needs
        visible = grown_visible_fraction(0.0, int(needs["visible_anchors"]), anchor_capacity, headroom=FIT_HEADROOM)
        decoded = num_visible_slots(anchor_capacity, visible) * n_offsets
        active = grown_active_fraction(0.0, int(needs["active_gaussians"]), decoded, headroom=1.15)
        num_active = cls(visible, active, 1.0).active_gaussians(anchor_capacity, n_offsets)
        per = max(1.25 * (int(needs["pairs"]) - PAIR_SLACK) / max(num_active, 1), 0.5)
        return cls(visible, active, math.ceil(per * 2.0) / 2.0)

    def regrown(self, old_capacity: int, new_capacity: int, n_offsets: int) -> Capacities:
        """These capacities for a model whose anchor capacity grew from ``old_capacity`` to ``new_capacity``.

        The visible slots widen with A (the fraction is kept: the grown anchors will be seen). The active
        Gaussians do not: the active fraction becomes the least multiple of 1/16 of the wider S·N that still
        holds the G_act the step had, and P (``pairs_per_active`` per active Gaussian) holds its pairs too. A
        growth adds anchors, not active Gaussians per view in proportion to the slots; keeping the fraction
        made every step after it pay for 1.5× the active Gaussians and pairs it used. A view that needs more
        is replayed as ever (:meth:`grown`). The pair capacity changes no number of a step that fits it; the
        active one changes the length of arrays XLA sums over, so the numbers may move by float rounding from the
        growth on (the README's main job did not). A shrink or an unchanged A gives these capacities back.
        """
        if new_capacity <= old_capacity:
            return self
        held = self.active_gaussians(old_capacity, n_offsets)
        decoded = self.visible_slots(new_capacity) * n_offsets
        fraction = ((held - 1) * ACTIVE_BUCKET // decoded + 1) / ACTIVE_BUCKET  # least k: ceil(k·S·N/16) ≥ G_act
        return dataclasses.replace(self, active_fraction=min(self.active_fraction, max(fraction, 1.0 / ACTIVE_BUCKET)))

    def for_evaluation(self) -> Capacities:
        """The capacities an evaluation render starts from: these with :data:`EVAL_HEADROOM` × the visible
        slots (in buckets of 1/8 of A; the active Gaussians and tile pairs scale with them).

        Held-out views may see more than the training views the step was fitted to, and the model grows
        between evaluations; each overflow would cost the render a recompilation (a replayed step grows
        the step's own capacities, not the evaluation's), while the extra slots cost a few held-out
        renders next to thousands of steps.
        """
        visible = min(1.0, math.ceil(EVAL_HEADROOM * self.visible_fraction * FRACTION_BUCKET) / FRACTION_BUCKET)
        return dataclasses.replace(self, visible_fraction=max(visible, self.visible_fraction))

    def union(self, other: Capacities) -> Capacities:
        """The capacities that hold what these and ``other`` hold: each fraction the larger (visible slots, active
        Gaussians and pairs all grow with their fraction)."""
        return Capacities(max(self.visible_fraction, other.visible_fraction),
                          max(self.active_fraction, other.active_fraction),
                          max(self.pairs_per_active, other.pairs_per_active))

    def as_dict(self) -> dict:
        """Checkpoint metadata and ``eval.json``'s ``capacities``."""
        return dataclasses.asdict(self)

    def restored(self, saved: dict | None) -> Capacities:
        """These capacities, never smaller than those of checkpoint metadata ``saved``.

        Metadata written before active-Gaussian compaction (``max_pairs_per_gaussian`` per
        decoded Gaussian, no active fraction) restores the visible fraction only.
        """
        if not saved:
            return self
        grown = dict(visible_fraction=max(self.visible_fraction, float(saved["visible_fraction"])))
        if "active_fraction" in saved:
            grown.update(active_fraction=max(self.active_fraction, float(saved["active_fraction"])),
                         pairs_per_active=max(self.pairs_per_active, float(saved["pairs_per_active"])))
        return dataclasses.replace(self, **grown)


@dataclasses.dataclass
class ExactRender:
    """A jitted render that never returns a truncated image.

    ``build(capacities)`` returns a jitted ``fn(anchors, ...) -> (*outputs, metrics)`` rendering
    ``anchors`` with those capacities, where ``metrics`` holds the render's ``dropped_*`` counts
    and what was needed (the keys :meth:`Capacities.grown` reads). Calling this object returns
    ``outputs`` (a tuple); when work was dropped it grows its capacities, rebuilds and renders
    again (``growths`` counts it). It starts from the capacities it is given, or, given none,
    from the need of the first call's view measured by ``fit`` (:meth:`Capacities.fitted`), and
    keeps the grown ones for the next call.
    """

    build: Callable[[Capacities], Callable]
    capacities: Capacities | None
    n_offsets: int
    growths: int = 0
    fn: Callable | None = None
    fit: Callable | None = None  # fit(anchors, *args) -> needs, for capacities=None: sized on the first call
    wrap: Callable[[Callable], Callable] = lambda fn: fn  # e.g. app.ahead.Program: compiled ahead of its calls

    def program(self) -> Callable:
        """The (wrapped) jitted render for the current capacities, built on first use."""
        if self.fn is None:
            self.fn = self.wrap(self.build(self.capacities))
        return self.fn

    def __call__(self, anchors, *args):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((anchors, args))):
            raise TypeError("this render is host-side (it reads what each view needed and grows its capacities "
                            "between calls), so it cannot run under jax.jit, jax.vmap or jax.grad: use "
                            "cusgs_jax.render(model, cameras, capacities=cusgs_jax.fit_render(model, cameras)), "
                            "which is traceable (docs/api.md#render-a-trained-model)")
        if self.capacities is None:
            self.capacities = Capacities.fitted(self.fit(anchors, *args), anchors.capacity, self.n_offsets)
        while True:
            *outputs, metrics = self.program()(anchors, *args)
            metrics = {k: int(v) for k, v in metrics.items()}
            if not any(metrics[k] for k in ("dropped_anchors", "dropped_gaussians", "dropped_pairs")):
                return tuple(outputs)
            self.capacities = self.capacities.grown(metrics, anchors.capacity, self.n_offsets)
            self.fn, self.growths = None, self.growths + 1
