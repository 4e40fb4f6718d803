"""Rendering a model for training and evaluation: decoded Gaussians → the splatter.

Naming (:mod:`cusgs_jax.types`): G Gaussians, Q query channels, H×W image, D feature dimension.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cusgs_jax.config import Config, SplatConfig
from cusgs_jax.model.anchors import AnchorState
from cusgs_jax.model.decode import Gaussians, VisibleSlots, decode_view
from cusgs_jax.model.field import retrieve
from cusgs_jax.model.queries import decode_queries
from cusgs_jax.splat import RenderOutput, rasterize
from cusgs_jax.training.capacity import ExactRender, max_pairs
from cusgs_jax.types import Camera


def render_gaussians(gaussians: Gaussians, camera: Camera, cfg: SplatConfig, means2d_delta=None,
                     extra_channels=None) -> RenderOutput:
    """Rasterise decoded Gaussians with the configured splatter settings.

    Args:
      extra_channels: [G, Q] or None, composited in the same pass after RGB
        (background 0), e.g. the feature queries; ``image`` is then [H, W, 3+Q].
    """
    num = gaussians.means.shape[0]
    colors, background = gaussians.colors, jnp.asarray(cfg.background, jnp.float32)
    if extra_channels is not None:
        colors = jnp.concatenate([colors, extra_channels], axis=-1)
        background = jnp.concatenate([background, jnp.zeros(extra_channels.shape[-1], jnp.float32)])
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, colors,
                     camera.world_to_camera, camera.K, camera.width, camera.height, background=background,
                     antialiased=cfg.antialiased, tile_size=cfg.tile_size, chunk_size=cfg.chunk_size,
                     max_pairs=max_pairs(cfg.max_pairs_per_gaussian, num), means2d_delta=means2d_delta)


def view_queries(nets: dict, anchors: AnchorState, view: VisibleSlots, camera: Camera, appearance_index,
                 cfg: Config) -> jax.Array:
    """[S·N, Q] per-Gaussian feature queries of the decoded (gathered) anchors."""
    gathered = jax.tree_util.tree_map(lambda x: x[view.slots], anchors.params)
    direction = anchors.centers[view.slots] - camera.center
    direction = direction / jnp.maximum(jnp.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
    appearance = nets["appearance"][appearance_index] if cfg.model.appearance else None
    return decode_queries(nets.get("queries"), gathered, direction, appearance)


def render_model(anchors: AnchorState, nets: dict, camera: Camera, appearance_index, cfg: Config,
                 banks: dict | None = None) -> tuple[RenderOutput, dict]:
    """Decode every visible slot at ``camera`` and rasterise (traceable; ``cfg`` from :func:`render_config`).

    Returns:
      (RenderOutput with ``image`` [H, W, 3] — [H, W, 3+Q] when ``banks`` is given —, features
      {model: [H, W, D]} retrieved through the memory heads, or {} without ``banks``).
    """
    gaussians, view = decode_view(nets, anchors, camera, appearance_index, cfg.model)
    queries = None if banks is None else view_queries(nets, anchors, view, camera, appearance_index, cfg)
    out = render_gaussians(gaussians, camera, cfg.splat, extra_channels=queries)
    features = {} if banks is None else retrieve(nets["memory"], banks, out.image[..., 3:], cfg.features)
    return out, features


def render_config(cfg: Config) -> Config:
    """The config for rendering a :func:`cusgs_jax.model.anchors.compact` model (every slot decoded)."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, visible_fraction=1.0))


def make_render_fn(cfg: Config) -> ExactRender:
    """``render(anchors, nets, camera, appearance_index) -> (rgb [H, W, 3] in [0, 1],)``.

    Meant for compacted anchors (:func:`cusgs_jax.model.anchors.compact`): every
    slot is decoded, and a render whose tile pairs would overflow is redone with
    a larger capacity (:class:`~cusgs_jax.training.capacity.ExactRender`), so the
    image is always exact.
    """
    def build(cfg: Config):
        cfg = render_config(cfg)

        @jax.jit
        def render(anchors, nets, camera, appearance_index):
            out, _ = render_model(anchors, nets, camera, appearance_index, cfg)
            return jnp.clip(out.image, 0.0, 1.0), out.overflow, out.num_pairs

        return render

    return ExactRender(build, cfg)


def make_feature_render_fn(cfg: Config) -> ExactRender:
    """``render(anchors, nets, camera, appearance_index, banks) -> (rgb [H,W,3], {model: [H,W,D]})``.

    Like :func:`make_render_fn`: every slot decoded, never a truncated render.
    """
    def build(cfg: Config):
        cfg = render_config(cfg)

        @jax.jit
        def render(anchors, nets, camera, appearance_index, banks):
            out, features = render_model(anchors, nets, camera, appearance_index, cfg, banks)
            return jnp.clip(out.image[..., :3], 0.0, 1.0), features, out.overflow, out.num_pairs

        return render

    return ExactRender(build, cfg)
