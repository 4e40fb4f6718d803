"""Sweeps beyond Hydra's grid: :mod:`cusgs_jax.sweep.pareto` (multi-objective Optuna search)."""
