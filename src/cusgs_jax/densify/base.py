"""What a strategy sees of one rendered view, and the strategies a configuration asks for.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, S visible slots, N Gaussians
per anchor, G = S·N, F latent size.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax

from cusgs_jax.config import Config
from cusgs_jax.model.decode import to_slots


@dataclasses.dataclass(frozen=True)
class ViewRecord:
    """One view of the train step, as the ``accumulate`` hooks see it (traced values).

    Attributes:
      slots: :class:`cusgs_jax.model.decode.VisibleSlots` (slots [S], valid [S]).
      gaussians: the decoded :class:`cusgs_jax.model.decode.Gaussians` (G = S·N, slot order).
      render: the splatter's :class:`cusgs_jax.splat.RenderOutput` (visible [G], significance [G]).
      grad2d: [G, 2] ∂L/∂μ_2D in pixels.
      latent_grad: [S, F] ∂L/∂z of the gathered anchors.
      capacity: A; width, height: image size.
      step: [] int32 steps completed before this one; finite: [] bool, the update is applied.
    """

    slots: Any
    gaussians: Any
    render: Any
    grad2d: jax.Array
    latent_grad: jax.Array
    capacity: int
    width: int
    height: int
    step: jax.Array
    finite: jax.Array

    def to_slots(self, x: jax.Array, fill=0) -> jax.Array:
        """Scatter per-visible-slot values [S, ...] back to anchor slots [A, ...] (others ``fill``)."""
        return to_slots(x, self.slots, self.capacity, fill)


class Strategy(Protocol):
    name: str

    def init_state(self, capacity: int) -> Any: ...

    def accumulate(self, stats: Any, view: ViewRecord) -> Any: ...

    def due(self, step: int) -> bool: ...

    def update(self, state, tx, step: int) -> tuple[Any, dict]: ...


def make_strategies(cfg: Config) -> tuple[Strategy, ...]:
    """Scaffold growing always; feature-aware pruning when ``prune.strategy == "feature_aware"``."""
    from cusgs_jax.densify.feature_prune import FeaturePruneStrategy
    from cusgs_jax.densify.scaffold import ScaffoldStrategy

    strategies: list[Strategy] = [ScaffoldStrategy(cfg.grow, cfg.model.voxel_size, cfg.model.n_offsets,
                                                   cfg.train.seed)]
    if cfg.prune.strategy == "feature_aware":
        strategies.append(FeaturePruneStrategy(cfg.prune))
    return tuple(strategies)
