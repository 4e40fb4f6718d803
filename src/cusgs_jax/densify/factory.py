"""The strategies a configuration asks for (its own module: the strategies import :mod:`.base`).

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets per anchor.
"""

from __future__ import annotations

from cusgs_jax.config import Config
from cusgs_jax.densify.base import Strategy
from cusgs_jax.densify.early_cull import EarlyCullStrategy
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy
from cusgs_jax.densify.scaffold import ScaffoldStrategy

__all__ = ["make_strategies"]


def make_strategies(cfg: Config) -> tuple[Strategy, ...]:
    """Early culling when ``grow.early_cull == "on"`` (``auto`` is resolved by the run for its scene,
    :func:`~cusgs_jax.densify.early_cull.resolve_early_cull`; unresolved it is off), Scaffold growing always,
    feature-aware pruning when ``prune.strategy == "feature_aware"``."""
    strategies: list[Strategy] = [EarlyCullStrategy(cfg.grow)] if cfg.grow.early_cull == "on" else []
    strategies.append(ScaffoldStrategy(cfg.grow, cfg.model.voxel_size, cfg.model.n_offsets, cfg.train.seed,
                                       ladder=cfg.model.capacity_ladder))
    if cfg.prune.strategy == "feature_aware":
        strategies.append(FeaturePruneStrategy(cfg.prune))
    return tuple(strategies)
