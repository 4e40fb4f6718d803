"""Validation helpers of the frozen configuration (:mod:`cusgs_jax.config`) and its readers:
one :class:`~cusgs_jax.errors.ConfigError` message per bad option, naming the option and the fix."""

from __future__ import annotations

import dataclasses
import math

from cusgs_jax.errors import ConfigError


def require(ok: bool, option: str, value, requirement: str, fix: str = "") -> None:
    """Raise :class:`ConfigError` ``"option=value: requirement; fix"`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{option}={value!r}: {requirement}" + (f"; {fix}" if fix else ""))


def finite_number(value) -> bool:
    """A real, finite int or float (not a bool, not NaN or ±inf)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def at_least(obj, prefix: str, minimum, *names: str) -> None:
    """Every named field of ``obj`` is a finite number ≥ ``minimum``."""
    for name in names:
        value = getattr(obj, name)
        require(finite_number(value) and value >= minimum, f"{prefix}.{name}", value, f"must be a number >= {minimum}")


def lists_to_tuples(obj) -> None:
    """Lists handed in by OmegaConf become tuples (frozen configs stay hashable)."""
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if isinstance(value, list):
            object.__setattr__(obj, field.name, tuple(value))


def require_config(cfg, where: str) -> None:
    """TypeError naming ``where`` when ``cfg`` is not a :class:`cusgs_jax.config.Config` (a dict, an OmegaConf
    node, None): research code calling the library gets the argument named, not an AttributeError deep inside."""
    kind = type(cfg)
    if (kind.__module__, kind.__name__) != ("cusgs_jax.config", "Config"):  # by name: config imports this module
        hint = ("convert it with from_omegaconf(cfg)" if type(cfg).__name__ == "DictConfig"
                else "build one with Config() or compose_config([...overrides])")
        raise TypeError(f"{where}: cfg must be a cusgs_jax.config.Config, got {type(cfg).__name__}: {hint}")
