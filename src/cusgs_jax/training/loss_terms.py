"""Loss terms of one's own: the extension point of the training loss (after nerfstudio's ``get_loss_dict``).

A :class:`LossTerm` is a name, a weight and a function ``fn(render, batch, state) -> []`` of

* ``render`` — a :class:`TermRender` of the view the step renders: ``image`` [H, W, 3] (RGB, not clipped),
  ``alpha`` [H, W], ``depth`` [H, W] (Σ z α T), and the decoded ``gaussians`` (:class:`~cusgs_jax.model.decode.Gaussians`,
  G = S·N of the view's visible slots, ``gaussians.active`` the ones the opacity mask keeps);
* ``batch`` — the step's batch of that view (:func:`~cusgs_jax.training.step.make_train_step`);
* ``state`` — the :class:`~cusgs_jax.training.state.TrainState` before the update (``state.step`` for a schedule).

The step adds ``weight · fn(...)`` to the loss and differentiates through it. The weight is an argument of the
step's program (``batch["loss_weights"][name]``, as the built-in weights are, :func:`term_weights`), so a sweep
over it shares one compiled step. The step reports every term unweighted (``metrics["loss_<name>"]``);
:func:`weighted_terms` weighs them on the host — the built-in ``l1``, ``ssim`` (1 − SSIM), ``volume`` and
``feature`` and the user's, which sum to the loss — and the loop logs them in ``metrics.jsonl`` and sums them over
the run in ``eval.json``'s ``loss_terms`` (``docs/api.md#a-loss-term-of-your-own``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

__all__ = ["LossTerm", "TermRender", "BUILT_IN_TERMS", "check_loss_terms", "term_weights", "weighted_terms",
           "LossTally"]

#: The built-in terms (``feature`` only with feature models), by the step metric that holds each one unweighted.
BUILT_IN_TERMS = ("l1", "ssim", "volume", "feature")
_METRIC = dict(l1="loss_l1", ssim="loss_ssim_loss", volume="loss_volume", feature="loss_feature")
_RESERVED = frozenset(BUILT_IN_TERMS) | {"loss", "image", "ssim_loss", "psnr", "terms"}


class TermRender(NamedTuple):
    """What a loss term sees of the rendered view (traced arrays).

    Attributes:
      image: [H, W, 3] rendered RGB (composited over the background, not clipped).
      alpha: [H, W] accumulated opacity 1 − T_final.
      depth: [H, W] alpha-weighted camera depth Σ z α T (divide by ``alpha`` for the expected depth).
      gaussians: the decoded :class:`~cusgs_jax.model.decode.Gaussians` of the view's S visible slots [G = S·N].
    """

    image: jax.Array
    alpha: jax.Array
    depth: jax.Array
    gaussians: Any


@dataclasses.dataclass(frozen=True)
class LossTerm:
    """A loss term of one's own: ``loss += weight · fn(render, batch, state)``.

    Attributes:
      name: a Python identifier, unique, none of the built-in names (:data:`BUILT_IN_TERMS`, ``loss``).
      fn: ``fn(render: TermRender, batch: dict, state: TrainState) -> []`` float, traceable and differentiable.
      weight: a finite number ≥ 0; passed to the step as an argument (``batch["loss_weights"][name]``).
    """

    name: str
    fn: Callable
    weight: float = 1.0


def check_loss_terms(terms) -> tuple[LossTerm, ...]:
    """``terms`` as a tuple, checked: each a :class:`LossTerm` with a callable ``fn``, an identifier name that no
    other term and no built-in one has, and a finite weight ≥ 0. Raises ValueError/TypeError naming the term."""
    terms = tuple(terms or ())
    seen = set()
    for term in terms:
        if not isinstance(term, LossTerm):
            raise TypeError(f"loss_terms: {term!r} is not a LossTerm; write LossTerm(name, fn, weight)")
        if not isinstance(term.name, str) or not term.name.isidentifier():
            raise ValueError(f"loss_terms: the name {term.name!r} is not a Python identifier (it becomes a "
                             "metrics.jsonl and eval.json key); use e.g. 'depth_tv'")
        if term.name in _RESERVED or term.name in seen:
            raise ValueError(f"loss_terms: the name {term.name!r} is already taken (built-in terms "
                             f"{', '.join(BUILT_IN_TERMS)}, and each term's name once); choose another")
        if not callable(term.fn):
            raise TypeError(f"loss_terms: the term {term.name!r} has fn={term.fn!r}, which is not callable; give a "
                            "function fn(render, batch, state) -> scalar")
        try:
            weight = float(term.weight)
        except (TypeError, ValueError):
            weight = math.nan
        if not (math.isfinite(weight) and weight >= 0):
            raise ValueError(f"loss_terms: the term {term.name!r} has weight {term.weight!r}; give a finite number "
                             ">= 0")
        seen.add(term.name)
    return terms


def term_weights(terms) -> dict[str, np.float32]:
    """``{name: weight}`` ([] float32) of the user's terms, the entries ``batch["loss_weights"]`` adds for them."""
    return {term.name: np.float32(term.weight) for term in terms}


def weighted_terms(metrics: dict, weights: dict) -> dict[str, float]:
    """Every loss term of a step's ``metrics`` (host values) times its weight: ``{"l1", "ssim", "volume"[,
    "feature"], <user terms>}`` as floats, which sum to ``metrics["loss"]`` (up to rounding). ``weights``: the
    step's ``loss_weights`` (:func:`cusgs_jax.training.step.loss_weights`)."""
    out = {}
    for name, weight in weights.items():
        key = _METRIC.get(name, f"loss_{name}")
        if key in metrics:
            out[name] = float(weight) * float(metrics[key])
    return out


@dataclasses.dataclass
class LossTally:
    """The weighted loss terms summed over a run's steps (``eval.json``'s ``loss_terms``; checkpointed).

    ``totals``: {term: Σ over the completed steps of its weighted value}; ``steps``: how many steps were added.
    """

    totals: dict[str, float] = dataclasses.field(default_factory=dict)
    steps: int = 0

    def add(self, terms: dict) -> None:
        """Add one completed step's ``metrics["terms"]`` (host values)."""
        for name, value in terms.items():
            self.totals[name] = self.totals.get(name, 0.0) + float(value)
        self.steps += 1

    def as_dict(self) -> dict:
        """``{"steps": n, "sum": {term: Σ}, "mean": {term: Σ / n}}`` (JSON)."""
        return dict(steps=self.steps, sum=dict(self.totals),
                    mean={name: total / max(self.steps, 1) for name, total in self.totals.items()})

    @classmethod
    def restored(cls, saved: dict | None) -> LossTally:
        """The tally of checkpoint metadata ``saved`` (:meth:`as_dict`), or an empty one."""
        if not saved:
            return cls()
        return cls(totals={k: float(v) for k, v in saved.get("sum", {}).items()}, steps=int(saved.get("steps", 0)))
