"""Render a trained model: ``render(model, cameras, capacities=fit_render(model, cameras))`` (after gsplat's
``rasterization()``): jit- and vmap-able, one view or a batch, image, alpha, depth and per-Gaussian meta.

The work of a view has static capacities (visible anchor slots, active Gaussians, tile pairs:
:class:`~cusgs_jax.training.capacity.Capacities`); :func:`fit_render` measures what the cameras need, outside
``jit``, once. :func:`render` is traceable: inside ``jit`` it cannot raise, so a view that would not fit reports
what it dropped in :attr:`Rendered.dropped` (the image is then truncated); outside ``jit`` it raises
:class:`RenderCapacityError` instead. Either way nothing is dropped silently.

The decoder's colour head takes a per-training-view appearance embedding; a new view borrows one (``appearance``):
``"nearest"`` (the nearest training camera's: the held-out protocol, recorded in ``eval.json`` as
:data:`APPEARANCE_PROTOCOL`), ``"mean"`` (the mean embedding) or an index into the training views.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, N offsets, G_act active Gaussians, B views, H×W image, D
feature dimension.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.io.load_run import TrainedModel
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.render import render_view, view_needs
from cusgs_jax.types import Camera, camera_center

__all__ = ["Rendered", "render", "fit_render", "RenderCapacityError", "appearance_index", "APPEARANCE_PROTOCOL"]

#: How the held-out evaluation chooses a new view's appearance embedding (``eval.json``'s ``appearance``).
APPEARANCE_PROTOCOL = "nearest"


class RenderCapacityError(ValueError):
    """A view needed more than the capacities it was rendered with (outside ``jit``)."""


class Rendered(NamedTuple):
    """What :func:`render` returns (a pytree; a batch of cameras adds a leading axis B to every entry).

    Attributes:
      image: [H, W, 3] RGB in [0, 1] (clipped, as the evaluation scores it).
      alpha: [H, W] accumulated opacity.
      depth: [H, W] alpha-weighted camera depth Σ z α T (divide by ``alpha`` for the expected depth).
      features: {feature model: [H, W, D]} read out through the memory heads (``features=True``), else {}.
      means2d: [G_act, 2] projected centres of the active Gaussians (gsplat's ``meta["means2d"]``).
      radii: [G_act, 2] int32 pixel half-extents (0: not drawn).
      ids: [G_act] int32 which Gaussian each entry is, ``anchor · N + offset`` (-1: an empty entry).
      dropped: {"anchors", "gaussians", "pairs"} [] int32 work that did not fit the capacities (0: exact).
    """

    image: jax.Array
    alpha: jax.Array
    depth: jax.Array
    features: dict
    means2d: jax.Array
    radii: jax.Array
    ids: jax.Array
    dropped: dict


def appearance_index(appearance, train_centers, center):
    """The training view whose appearance embedding a camera at ``center`` [3] borrows (traceable; NumPy in,
    NumPy out): ``"nearest"`` the training camera nearest to it (``train_centers`` [V, 3]), an int that index."""
    if isinstance(appearance, str):
        if appearance != "nearest":
            raise ValueError(f"appearance={appearance!r}: give 'nearest', 'mean' or a training view's index")
        xp = np if isinstance(center, np.ndarray) and isinstance(train_centers, np.ndarray) else jnp
        return xp.argmin(xp.linalg.norm(train_centers - center, axis=-1)).astype(xp.int32)
    return jnp.int32(appearance)


def fit_render(model: TrainedModel, cameras: Camera, *, appearance="nearest") -> Capacities:
    """The capacities that every view of ``cameras`` (one or a batch) fits, with headroom (outside ``jit``: one
    program measures every view's need, :func:`cusgs_jax.training.render.view_needs`)."""
    _check_model(model)
    count = _batch_size(cameras)
    views = [_one(cameras, b) for b in range(count)] if count else [cameras]
    nets, centers = _nets(model, appearance), _train_centers(model)
    needs = view_needs(model.anchors, nets, [(view, _index(appearance, centers, view)) for view in views],
                       model.cfg)
    most = {key: max(need[key] for need in needs) for key in needs[0]}
    return Capacities.fitted(most, model.anchors.capacity, model.cfg.model.n_offsets)


def render(model: TrainedModel, cameras: Camera, *, capacities: Capacities, appearance="nearest",
           features: bool = False) -> Rendered:
    """Render ``model`` from ``cameras`` (a :class:`~cusgs_jax.types.Camera`, or a batch of them: ``K`` [B, 3, 3],
    ``world_to_camera`` [B, 4, 4]). Traceable: ``jax.jit`` and ``jax.vmap`` of a function that calls it work
    (the model's arrays are closed over or passed; ``capacities`` and ``appearance`` are static).

    Args:
      model: a trained model (:func:`cusgs_jax.train`'s or :func:`cusgs_jax.load_trained`'s).
      capacities: from :func:`fit_render`. Not ``eval.json``'s ``capacities``: those are fractions of the
        training run's anchor capacity, and a loaded model is compacted to fewer slots, so they can drop work.
      appearance: ``"nearest"`` (the held-out protocol), ``"mean"`` or a training view's index.
      features: also read out the feature maps (a model trained with feature models).
    Returns:
      :class:`Rendered`.
    Raises:
      RenderCapacityError: outside ``jit``, a view that did not fit ``capacities`` (fit them to these cameras).
    """
    _check_model(model)
    if features and not model.banks:
        raise ValueError("render(features=True): the model has no feature models (no PSC banks)")
    nets = _nets(model, appearance)
    banks = {name: jnp.asarray(bank) for name, bank in model.banks.items()} if features else None
    out = _render(model.anchors, nets, _train_centers(model), banks, cameras, cfg=model.cfg, capacities=capacities,
                  appearance=appearance if isinstance(appearance, str) else int(appearance),
                  batched=bool(_batch_size(cameras)))
    if not isinstance(out.image, jax.core.Tracer):  # outside jit: a truncated view is an error, never silent
        dropped = {key: int(np.max(np.asarray(value))) for key, value in out.dropped.items()}
        if any(dropped.values()):
            raise RenderCapacityError(f"render: the capacities {capacities} dropped work ({dropped}): fit them to "
                                      "these cameras, capacities=cusgs_jax.fit_render(model, cameras)")
    return out


@functools.partial(jax.jit, static_argnames=("cfg", "capacities", "appearance", "batched"))
def _render(anchors, nets, centers, banks, cameras, *, cfg, capacities, appearance, batched):
    def one(camera):
        index = (jnp.int32(0) if appearance == "mean"
                 else appearance_index(appearance, centers, camera_center(camera.world_to_camera)))
        return _render_view(anchors, nets, camera, index, cfg, capacities, banks)

    # a batch: one view after another in one program (lax.map), as fast as separate calls on a CPU and the same
    # numbers as rendering each view alone; a caller's jax.vmap of render batches the views instead
    return jax.lax.map(one, cameras) if batched else one(cameras)


def _render_view(anchors, nets, camera, index, cfg, capacities: Capacities, banks) -> Rendered:
    """One view: :func:`cusgs_jax.training.render.render_model`'s pipeline, keeping the per-Gaussian meta."""
    out, feature_maps, view, chosen = render_view(anchors, nets, camera, index, cfg, capacities, banks)
    n = cfg.model.n_offsets
    ids = jnp.where(chosen.valid, view.slots[chosen.index // n] * n + chosen.index % n, -1).astype(jnp.int32)
    return Rendered(image=jnp.clip(out.image[..., :3], 0.0, 1.0), alpha=out.alpha, depth=out.depth,
                    features=feature_maps, means2d=out.means2d, radii=out.radii, ids=ids,
                    dropped=dict(anchors=view.overflow, gaussians=chosen.overflow, pairs=out.overflow))


def _check_model(model) -> None:
    if not isinstance(model, TrainedModel):
        raise TypeError(f"model: give a trained model (cusgs_jax.train(...).model or cusgs_jax.load_trained(run)), "
                        f"not {type(model).__name__}")


def _nets(model: TrainedModel, appearance) -> dict:
    """The networks with the appearance table a view borrows from: ``"mean"`` makes it the one mean row."""
    nets = dict(model.nets)
    if appearance == "mean" and "appearance" in nets:
        nets["appearance"] = jnp.mean(nets["appearance"], axis=0, keepdims=True)
    return nets


def _train_centers(model: TrainedModel):
    """[V, 3] the training cameras' centres (for ``appearance="nearest"``)."""
    if model.cameras is None:
        return jnp.zeros((1, 3), jnp.float32)
    return jax.vmap(camera_center)(model.cameras.world_to_camera)


def _index(appearance, centers, camera: Camera):
    if appearance == "mean":
        return np.int32(0)
    return np.int32(appearance_index(appearance, np.asarray(centers), np.asarray(camera_center(camera.world_to_camera))))


def _batch_size(cameras: Camera) -> int:
    """B for a batch of cameras, 0 for one camera."""
    return int(cameras.world_to_camera.shape[0]) if np.ndim(cameras.world_to_camera) == 3 else 0


def _one(cameras: Camera, b: int) -> Camera:
    return jax.tree_util.tree_map(lambda x: x[b], cameras)
