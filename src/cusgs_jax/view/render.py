"""What the viewer renders, and the render itself: a model at any camera → :class:`~cusgs_jax.view.modes.Frame`.

:class:`ViewModel` is everything the viewer needs of a model: the configuration, compacted
anchors, networks (the appearance embedding replaced by the training views' mean, as the
exporter does for a view that is none of the training views), the PSC banks of the feature
models, and the list of cameras to jump to. It is frozen, and the viewer reads nothing else:
it comes from a run folder (:func:`from_trained`, through :func:`cusgs_jax.io.load_run.load_trained`)
or, for the live view of a training run, from the run's arrays as they are at a step
(:func:`view_model`, with the cameras of :func:`scene_cameras`; the training loop builds it).

:class:`ViewRenderer` renders it with our splatter (:func:`cusgs_jax.training.render.render_gaussians`,
every slot decoded, never a truncated image): RGB, alpha, alpha-weighted depth, and when asked the
rendered features of every feature model ([H, W, D] each, through the memory heads).

Naming: A anchor capacity, E appearance size, M PSC entries, D feature dimension, V views, H×W image.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import Config
from cusgs_jax.extract.optional import run_features
from cusgs_jax.training.capacity import ExactRender
from cusgs_jax.training.render import render_model, view_work_probe
from cusgs_jax.view.camera import scene_up
from cusgs_jax.view.modes import Frame

if TYPE_CHECKING:  # annotations only
    from cusgs_jax.data.scene_data import SceneData
    from cusgs_jax.io.load_run import TrainedModel
    from cusgs_jax.model.anchors import AnchorState
    from cusgs_jax.types import Camera

__all__ = ["ViewCamera", "ViewModel", "ViewRenderer", "from_trained", "mean_appearance_nets", "scene_cameras",
           "view_model"]

ViewCamera = tuple[str, np.ndarray, np.ndarray, int, int]
"""A camera to jump to: (label, K [3, 3], world→camera [4, 4], width W, height H)."""


@dataclasses.dataclass(frozen=True)
class ViewModel:
    """A model ready to view.

    Attributes:
      cfg: its :class:`~cusgs_jax.config.Config`.
      anchors: compacted :class:`~cusgs_jax.model.anchors.AnchorState`.
      nets: networks with ``appearance`` [1, E] (the mean embedding; index 0) when the model has one.
      banks: {model: [M, D]} jax arrays, or None (no feature model rendered).
      cameras: :data:`ViewCamera` s to jump to, training views first.
      center: [3] the middle of the alive anchors (orbit centre); up: [3] world up of the cameras.
    """

    cfg: Config
    anchors: AnchorState
    nets: dict[str, Any]
    banks: dict[str, jax.Array] | None
    cameras: list[ViewCamera]
    center: np.ndarray
    up: np.ndarray

    @property
    def feature_models(self) -> list[str]:
        """Names of the feature models the viewer can render (those with banks and memory heads)."""
        if self.banks is None or "memory" not in self.nets:
            return []
        return [m.name for m in self.cfg.features.model_list if m.name in self.banks]


def mean_appearance_nets(nets: dict[str, Any]) -> dict[str, Any]:
    """``nets`` with the appearance table [V, E] replaced by its mean [1, E] (render with index 0)."""
    if "appearance" not in nets:
        return nets
    return {**nets, "appearance": jnp.mean(nets["appearance"], axis=0, keepdims=True)}


def _camera_list(prefix: str, cameras: Camera | None) -> list[ViewCamera]:
    """``cameras`` (batched: K [V, 3, 3], world_to_camera [V, 4, 4]) as labelled :data:`ViewCamera` s."""
    if cameras is None:
        return []
    Ks, viewmats = np.asarray(cameras.K), np.asarray(cameras.world_to_camera)
    return [(f"{prefix} {i}", Ks[i], viewmats[i], int(cameras.width), int(cameras.height)) for i in range(len(Ks))]


def scene_cameras(scene: SceneData, train_idx: np.ndarray) -> list[ViewCamera]:
    """The cameras of a loaded scene to jump to: the training views ``train_idx`` [V] ("train i"), then the
    scene's held-out views ("held-out i"), in the frame the scene is in."""
    cameras = []
    for prefix, idx in (("train", train_idx), ("held-out", scene.test_indices)):
        if len(idx):
            Ks, viewmats = np.asarray(scene.Ks)[idx], np.asarray(scene.viewmats)[idx]
            cameras += [(f"{prefix} {i}", Ks[i], viewmats[i], int(scene.width), int(scene.height))
                        for i in range(len(idx))]
    return cameras


def view_model(cfg: Config, anchors: AnchorState, nets: dict[str, Any], banks: dict[str, Any] | None,
               cameras: list[ViewCamera]) -> ViewModel:
    """The :class:`ViewModel` of a model's arrays: ``anchors`` compacted
    (:func:`~cusgs_jax.model.anchors.compact`), ``nets`` with the per-view appearance table [V, E] (replaced
    here by its mean), ``banks`` {model: [M, D]} (NumPy or jax) or None, ``cameras`` to jump to."""
    alive = np.asarray(anchors.alive)
    centers = np.asarray(anchors.centers)[alive]
    center = centers.mean(axis=0) if len(centers) else np.zeros(3)
    up = scene_up(np.stack([c[2] for c in cameras])) if cameras else np.array([0.0, -1.0, 0.0])
    banks = None if banks is None else {name: jnp.asarray(b) for name, b in banks.items()}
    return ViewModel(cfg=cfg, anchors=anchors, nets=mean_appearance_nets(nets), banks=banks, cameras=cameras,
                     center=center, up=up)


def from_trained(model: TrainedModel) -> ViewModel:
    """The :class:`ViewModel` of a :class:`~cusgs_jax.io.load_run.TrainedModel` (its run folder only).

    Cameras: the training views, then the held-out views, as the checkpoint records them.
    """
    cfg = model.cfg
    if model.banks:  # a cusgs-train run's .hydra config: resolve its feature models as setup did
        cfg = cfg.replace(features=run_features(cfg))
    banks = model.banks if cfg.features.enabled else None
    cameras = _camera_list("train", model.cameras) + _camera_list("held-out", model.held_out_cameras)
    return view_model(cfg, model.anchors, model.nets, banks, cameras)


class ViewRenderer:
    """Renders a :class:`ViewModel` at a camera (jitted once per image size; pair capacity grown as needed)."""

    def __init__(self, cfg: Config):
        probe = view_work_probe(cfg)
        # The viewer's render takes (anchors, nets, camera, banks) and always the mean appearance, index 0.
        self._render = ExactRender(lambda capacities: _build(cfg, capacities), None, cfg.model.n_offsets,
                                   fit=lambda anchors, nets, camera, banks: probe(anchors, nets, camera, 0))

    def render(self, model: ViewModel, camera: Camera, *, features: bool = False) -> Frame:
        """:class:`~cusgs_jax.view.modes.Frame` of ``model`` at ``camera``; ``features``: also every feature model's."""
        banks = model.banks if features and model.feature_models else None
        rgb, depth, alpha, feats = self._render(model.anchors, model.nets, camera, banks)
        return Frame(rgb=np.asarray(rgb), depth=np.asarray(depth), alpha=np.asarray(alpha),
                     features={name: np.asarray(f) for name, f in feats.items()})


def _build(cfg: Config, capacities):
    """``build(capacities)`` for :class:`~cusgs_jax.training.capacity.ExactRender`: ``render(anchors, nets, camera,
    banks or None) -> (rgb [H,W,3], depth [H,W], alpha [H,W], {model: [H,W,D]}, work metrics)`` with the
    mean appearance embedding (index 0 of :func:`mean_appearance_nets`)."""
    @jax.jit
    def render(anchors, nets, camera, banks):
        out, feats, work = render_model(anchors, nets, camera, jnp.int32(0), cfg, capacities, banks)
        return jnp.clip(out.image[..., :3], 0.0, 1.0), out.depth, out.alpha, feats, work

    return render
