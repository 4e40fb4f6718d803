"""A run's configuration resolved once, for its scene: every ``auto`` (or unset) setting replaced.

:func:`resolve_for_scene` is the one place a run turns the user's :class:`~cusgs_jax.config.Config` into
the one it trains with; it returns that configuration with the facts of the scene it was resolved from
(:class:`Resolved`). The rules themselves live beside what they decide: the feature models
(:func:`cusgs_jax.extract.optional.run_features`), the background (:func:`cusgs_jax.training.inputs.resolve_background`),
the voxel size (:func:`resolve_voxel_size` here: the spacing rules are :func:`cusgs_jax.model.anchors.auto_voxel_size`
and :func:`cusgs_jax.data.random_points.random_voxel_size`) and early culling
(:func:`cusgs_jax.densify.early_cull.resolve_early_cull`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import NamedTuple

import numpy as np

from cusgs_jax.config import Config
from cusgs_jax.data.random_points import random_voxel_size
from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.densify.early_cull import resolve_early_cull
from cusgs_jax.extract.optional import run_features
from cusgs_jax.model.anchors import auto_voxel_size
from cusgs_jax.training.inputs import resolve_background

__all__ = ["Resolved", "SceneFacts", "resolve_for_scene", "resolve_voxel_size"]

log = logging.getLogger("cusgs_jax")


class SceneFacts(NamedTuple):
    """What the resolution read of the scene.

    Attributes:
      demo: the built-in demo scene (``data.path`` not set): ``features.models=auto`` trains the demo's models.
      layout: ``SceneData.dataset_format``; background: the colour its images were composited on.
      random_start: the initial points are random (a layout without points): the voxel size comes from the
        cameras.
      carved_by_coverage: carving dropped random points by the views' alpha (``SceneData.carving``: some
        training view carries alpha); ``grow.early_cull=auto`` is on for a random start without it.
      points: the initial points' count.
    """

    demo: bool
    layout: str
    background: tuple[float, float, float]
    random_start: bool
    carved_by_coverage: bool
    points: int


class Resolved(NamedTuple):
    """The configuration a run trains with (no ``auto`` left) and the facts it was resolved from."""

    cfg: Config
    facts: SceneFacts


def resolve_for_scene(cfg: Config, scene: SceneData) -> Resolved:
    """``cfg`` with ``features.models``, ``splat.background``, ``model.voxel_size`` and ``grow.early_cull``
    resolved for ``scene`` (in the training frame); settings the user gave are kept."""
    facts = SceneFacts(demo=not cfg.data.path, layout=scene.dataset_format,
                       background=tuple(float(c) for c in scene.background),
                       random_start=scene.random_points is not None,
                       carved_by_coverage=scene.carving is not None and scene.carving.views_with_alpha > 0,
                       points=len(scene.points))
    cfg = dataclasses.replace(cfg, features=run_features(cfg))
    cfg = resolve_background(cfg, scene)  # splat.background not set: the layout's default (white for Blender)
    train = scene.train_indices
    cfg = resolve_voxel_size(cfg, scene.points, (scene.viewmats[train], scene.Ks[train], scene.width, scene.height)
                             if facts.random_start else None)
    return Resolved(resolve_early_cull(cfg, facts.random_start, facts.carved_by_coverage), facts)


def resolve_voxel_size(cfg: Config, points: np.ndarray, random_cameras: tuple | None = None) -> Config:
    """``cfg`` with ``model.voxel_size=None`` (auto) replaced by :func:`auto_voxel_size` of ``points`` [P, 3] —
    or, when ``random_cameras`` = (viewmats [V, 4, 4], Ks [V, 3, 3], width, height) is given (the points are
    random, not SfM: a layout without points), by
    :func:`cusgs_jax.data.random_points.random_voxel_size` of those cameras, since the spacing of
    uniform random points says how many there are, not how fine the scene is. A set size is kept."""
    if cfg.model.voxel_size is not None:
        return cfg
    if random_cameras is not None:
        size = random_voxel_size(*random_cameras)
        log.info("model.voxel_size=auto: %.5g (half a pixel's footprint at the distance the cameras look at; "
                 "the %d initial points are random)", size, len(points))
    else:
        size = auto_voxel_size(points)
        log.info("model.voxel_size=auto: %.5g (median nearest-neighbour spacing of the %d initial points)", size,
                 len(points))
    return cfg.replace(model=dict(voxel_size=size))
