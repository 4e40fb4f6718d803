"""Composing a :class:`~cusgs_jax.config.Config` the way ``cusgs-train`` does: Hydra's schema, the YAML spellings.

Hydra's schema is built from the frozen classes of :mod:`cusgs_jax.config` (:class:`HydraSchema`, registered as
``base_config`` by :func:`register_configs`); unknown keys and values of the wrong type are rejected by Hydra
against it. :func:`from_dict`, which every composed or stored configuration passes, converts the two YAML
spellings of :data:`YAML_SPELLINGS`: ``model.voxel_size=auto`` → None, ``features.models`` = ``auto`` / ``demo``
/ a list of dicts → None / :data:`~cusgs_jax.config.DEMO_FEATURE_MODELS` / a tuple of
:class:`~cusgs_jax.config.FeatureModelConfig`. :func:`compose_config` is the command line's composition in Python.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Optional

from cusgs_jax.checks import finite_number as _number, require
from cusgs_jax.config import DEMO_FEATURE_MODELS, Config, FeatureModelConfig, unknown_option
from cusgs_jax.errors import ConfigError

__all__ = ["HydraSchema", "YAML_SPELLINGS", "compose_config", "compose_node", "composition_error", "from_dict",
           "from_omegaconf", "register_configs"]


def _feature_model(values) -> FeatureModelConfig:
    """One ``features.models`` entry as YAML gives it: a dict of :class:`FeatureModelConfig` fields."""
    known = [f.name for f in dataclasses.fields(FeatureModelConfig)]
    require(isinstance(values, dict), "features.models", values, f"each model must be a mapping of {known}",
            "e.g. 'features.models=[{name: daisy}]'")
    unknown = sorted(set(values) - set(known))
    require(not unknown, "features.models", values, f"unknown key(s) {unknown}; each model takes {known}")
    return FeatureModelConfig(**values)


def _voxel_size_from_yaml(value) -> Optional[float]:
    """``model.voxel_size`` as YAML / the command line give it: ``auto`` (or null) → None, a number → float."""
    if value is None or value == "auto":
        return None
    require(_number(value) and value > 0, "model.voxel_size", value,
            "must be 'auto' or a cell size > 0 in units of the scene extent",
            "e.g. model.voxel_size=0.01 (1 % of the extent) or model.voxel_size=auto")
    return float(value)


def _feature_models_from_yaml(value) -> Optional[tuple[FeatureModelConfig, ...]]:
    """``features.models`` as YAML / the command line give it: ``auto`` (or null) → None, ``demo`` →
    :data:`DEMO_FEATURE_MODELS`, a list of dicts → a tuple of :class:`FeatureModelConfig`."""
    if value is None or value == "auto":
        return None
    if value == "demo":
        return DEMO_FEATURE_MODELS
    require(isinstance(value, (list, tuple)), "features.models", value, "must be 'auto', 'demo' or a list of "
            "models", "e.g. 'features.models=[{name: daisy}]'")
    return tuple(_feature_model(m) for m in value)


#: Options whose YAML / command-line spelling is not their typed value: (YAML → value, value → YAML).
YAML_SPELLINGS = {
    "model.voxel_size": (_voxel_size_from_yaml, lambda size: "auto" if size is None else size),
    "features.models": (_feature_models_from_yaml,
                        lambda models: "auto" if models is None else tuple(dataclasses.asdict(m) for m in models)),
}


class HydraSchema:
    """Hydra's schema of :class:`Config` (``base_config``): a mutable twin of each frozen class — Hydra
    must merge overrides into it, and frozen ones would reach it read-only — with the same fields,
    types and defaults, except that the :data:`YAML_SPELLINGS` options are typed ``Any`` and default to
    their YAML spelling (``model.voxel_size: auto``). The twins are attributes of this class
    (``HydraSchema.Config``, ``HydraSchema.ModelConfig``, …), so composed configs pickle (launchers)."""


def _twin(defaults, prefix: str = "") -> type:
    """The :class:`HydraSchema` twin of the config instance ``defaults`` (its values become the defaults)."""
    hints, spec, name = typing.get_type_hints(type(defaults)), [], type(defaults).__name__
    for field in dataclasses.fields(defaults):
        option, value = prefix + field.name, getattr(defaults, field.name)
        if dataclasses.is_dataclass(value):
            spec.append((field.name, (twin := _twin(value, f"{option}.")), dataclasses.field(default_factory=twin)))
        elif option in YAML_SPELLINGS:
            spec.append((field.name, Any, dataclasses.field(default=YAML_SPELLINGS[option][1](value))))
        else:
            spec.append((field.name, hints[field.name], dataclasses.field(default=value)))
    twin = dataclasses.make_dataclass(name, spec, namespace={"__module__": __name__,
                                                             "__qualname__": f"HydraSchema.{name}"})
    setattr(HydraSchema, name, twin)
    return twin


_twin(Config())


def register_configs() -> None:
    """Register :class:`HydraSchema` (:class:`Config` with its defaults) as Hydra's ``base_config`` schema."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="base_config", node=HydraSchema.Config)


def from_omegaconf(cfg) -> Config:
    """The frozen :class:`Config` of a composed Hydra config (the ``hydra`` node ignored)."""
    from omegaconf import OmegaConf

    values = OmegaConf.to_container(cfg, resolve=True)
    values.pop("hydra", None)
    return from_dict(values)


def from_dict(values: dict) -> Config:
    """:class:`Config` from a nested dict of plain values (a composed Hydra config, a run's
    ``.hydra/config.yaml``, a checkpoint's record), the :data:`YAML_SPELLINGS` converted;
    an unknown key raises :class:`~cusgs_jax.errors.ConfigError` naming the nearest option."""
    return _build(Config, values, "")


def _build(cls, values: dict, prefix: str):
    values = dict(values or {})
    kwargs = {}
    for field in dataclasses.fields(cls):
        if field.name not in values:
            continue
        value = values.pop(field.name)
        sub = field.default_factory if field.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(sub) and isinstance(value, dict):
            value = _build(sub, value, f"{prefix}{field.name}.")
        elif prefix + field.name in YAML_SPELLINGS:
            value = YAML_SPELLINGS[prefix + field.name][0](value)
        kwargs[field.name] = value
    if values:  # the first unknown key, with the nearest option (a '+key=value' override, a hand-edited record)
        key = sorted(values)[0]
        raise unknown_option(prefix + key, values[key])
    return cls(**kwargs)


def compose_node(overrides: tuple[str, ...] | list[str] = (), return_hydra_config: bool = False):
    """The OmegaConf node ``cusgs-train <overrides>`` composes (Hydra's compose API); with
    ``return_hydra_config`` it also holds the ``hydra`` node (launcher, sweeper)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    register_configs()
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    with initialize_config_module("cusgs_jax.conf", version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=return_hydra_config)


def compose_config(overrides: tuple[str, ...] | list[str] = ()) -> Config:
    """The :class:`Config` that ``cusgs-train <overrides>`` would run (Hydra's compose API).

    Raises:
      ConfigError: an override that cannot compose, in one line as the command line says it: an unknown key
        names the nearest option (:func:`~cusgs_jax.config.unknown_option`; never Hydra's ``+key`` advice, which
        only moves the refusal), an unknown group option lists the options there are.
    """
    from hydra.errors import ConfigCompositionException

    try:
        node = compose_node(overrides)
    except ConfigCompositionException as error:
        raise composition_error(error, overrides) from None
    return from_omegaconf(node)


#: The Hydra plugin each optional launcher needs, and the extra that installs it.
LAUNCHER_EXTRAS = {"hydra/launcher/ray": "ray", "hydra/launcher/submitit": "slurm"}


def composition_error(error: Exception, overrides=()) -> ConfigError:
    """One-line :class:`ConfigError` for Hydra's composition ``error`` of ``overrides``, with the fix."""
    from hydra.errors import MissingConfigException

    if isinstance(error, MissingConfigException):  # an unknown group option (experiment=nope, hydra/launcher=ray)
        first = str(error).split("\n\n")[0]
        options = _listed_options(str(error))
        extra = next((name for key, name in LAUNCHER_EXTRAS.items() if f"'{key}" in first), None)
        hint = f"; the plugin comes with the {extra} extra: pip install -e \".[{extra}]\"" if extra else ""
        return ConfigError((f"{first}; choose one of {options}" if options else first) + hint)
    cause = error.__cause__
    head = str(error).splitlines()[0]
    if cause is None:
        return ConfigError(head)
    detail = str(cause).splitlines()[0]
    full_key = str(getattr(cause, "full_key", "") or "")
    if type(cause).__name__ in ("ConfigAttributeError", "ConfigKeyError"):
        if full_key and not full_key.startswith("hydra."):
            given = [o.split("=", 1) for o in overrides if "=" in o]  # the override naming it (trian: trian.iterations)
            given = [(key.lstrip("+~"), value) for key, value in given
                     if key.lstrip("+~") == full_key or key.lstrip("+~").startswith(full_key + ".")]
            return unknown_option(*given[-1][:1], shown=given[-1][1]) if given else unknown_option(full_key)
        return ConfigError(f"unknown option {full_key or head}: {detail}; `cusgs-train --cfg hydra` lists Hydra's "
                           "options")
    return ConfigError(f"{head}: {detail}" + (f" (option {full_key})" if full_key else ""))


def _listed_options(message: str) -> list[str]:
    """The tab-indented names under Hydra's "Available options in 'group':" line."""
    lines = message.split("Available options", 1)[-1].splitlines()[1:] if "Available options" in message else []
    options = []
    for line in lines:
        if not line.startswith("\t"):
            break
        options.append(line.strip())
    return options
