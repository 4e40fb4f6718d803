"""The strategies a configuration asks for (its own module: the strategies import :mod:`.base`).

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets per anchor.
"""

from __future__ import annotations

from cusgs_jax.config import Config
from cusgs_jax.densify.base import Strategy
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy
from cusgs_jax.densify.scaffold import ScaffoldStrategy

__all__ = ["make_strategies"]


def make_strategies(cfg: Config) -> tuple[Strategy, ...]:
    """Scaffold growing always; feature-aware pruning when ``prune.strategy == "feature_aware"``."""
    strategies: list[Strategy] = [ScaffoldStrategy(cfg.grow, cfg.model.voxel_size, cfg.model.n_offsets,
                                                   cfg.train.seed)]
    if cfg.prune.strategy == "feature_aware":
        strategies.append(FeaturePruneStrategy(cfg.prune))
    return tuple(strategies)
