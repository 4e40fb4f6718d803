"""Rendering a model for training and evaluation: decoded Gaussians → the splatter.

Naming (:mod:`cusgs_jax.types`): G Gaussians, Q query channels, H×W image, D feature dimension.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import Config, SplatConfig
from cusgs_jax.model.anchors import AnchorState
from cusgs_jax.model.active import ActiveSet, compact_gaussians, gather_active, select_active
from cusgs_jax.model.decode import (Gaussians, ViewInputs, VisibleSlots, decode_inputs, decode_view,
                                    gather_visible, view_inputs, visible_slots)
from cusgs_jax.model.field import retrieve
from cusgs_jax.model.queries import decode_queries
from cusgs_jax.splat import Compositor, RenderOutput, SparseChannels, rasterize
from cusgs_jax.splat.project import project_gaussians
from cusgs_jax.splat.tiles import TileGrid, count_pairs
from cusgs_jax.training.capacity import Capacities, ExactRender, max_pairs
from cusgs_jax.types import Camera


def render_gaussians(gaussians: Gaussians, camera: Camera, cfg: SplatConfig, *, active_capacity: int | None = None,
                     pair_capacity: int | None = None, means2d_delta=None,
                     extra_channels=None, extra_pixels: tuple[int, ...] | None = None,
                     ) -> tuple[RenderOutput, ActiveSet]:
    """Rasterise the active decoded Gaussians with the configured splatter settings.

    Only the Gaussians that pass the opacity mask (``gaussians.active``) are rasterised: they
    are gathered into G_act = ``active_capacity`` entries first (:mod:`cusgs_jax.model.active`),
    so projection, sorting, binning and compositing pay for the active ones only.

    Args:
      gaussians: decoded Gaussians [G].
      active_capacity: static G_act (default G: nothing can be dropped).
      pair_capacity: static tile-pair capacity (default ``splat.max_pairs_per_gaussian`` per
        active entry, :func:`~cusgs_jax.training.capacity.max_pairs`).
      means2d_delta: [G_act, 2] or None (differentiate with respect to it for ∂L/∂μ_2D).
      extra_channels: [G, Q] or None, composited in the same pass after RGB
        (background 0), e.g. the feature queries; ``image`` is then [H, W, 3+Q].
      extra_pixels: static flat pixel indices (``row · W + column``) or None: the extra channels are composited
        there only and are 0 elsewhere (:class:`~cusgs_jax.splat.SparseChannels`; what the feature loss reads,
        :func:`~cusgs_jax.model.field.read_pixels`).
    Returns:
      (the render of the compacted Gaussians — per-Gaussian fields [G_act]; ``expand_render``
      maps them back to [G] —, the :class:`~cusgs_jax.model.active.ActiveSet`).
    """
    num = gaussians.means.shape[0]
    active_capacity = num if active_capacity is None else int(active_capacity)
    if pair_capacity is None:
        pair_capacity = max_pairs(cfg.max_pairs_per_gaussian, active_capacity)
    chosen = select_active(gaussians.active, active_capacity)
    compact = compact_gaussians(gaussians, chosen)
    colors, background = compact.colors, jnp.asarray(cfg.background_color, jnp.float32)
    if extra_channels is not None:
        colors = jnp.concatenate([colors, gather_active(extra_channels, chosen)], axis=-1)
        background = jnp.concatenate([background, jnp.zeros(extra_channels.shape[-1], jnp.float32)])
    out = rasterize(compact.means, compact.quats, compact.scales, compact.opacities, colors,
                    camera.world_to_camera, camera.K, camera.width, camera.height, background=background,
                    antialiased=cfg.antialiased, tile_size=cfg.tile_size, max_pairs=int(pair_capacity),
                    means2d_delta=means2d_delta, lens=camera.lens,
                    compositor=Compositor(cfg.backend, cfg.chunk_size, tiles=cfg.tiles),
                    sparse_channels=(None if extra_channels is None or extra_pixels is None
                                     else SparseChannels(int(extra_channels.shape[-1]), tuple(extra_pixels))))
    return out, chosen


def decode_view_inputs(nets: dict, inputs: ViewInputs, cfg: Config, *, queries: bool) -> tuple[Gaussians, jax.Array | None]:
    """The view's Gaussians [G = S·N] and, when ``queries``, their feature queries [G, Q] — both
    decoded from the one :class:`~cusgs_jax.model.decode.ViewInputs` bundle."""
    gaussians = decode_inputs(nets["decoder"], inputs, cfg.model.decoder())
    return gaussians, (decode_queries(nets.get("queries"), inputs, cfg.model.matmul_precision) if queries else None)


def work_metrics(view: VisibleSlots, chosen: ActiveSet, out: RenderOutput) -> dict:
    """What one view needed and what did not fit (the keys :meth:`Capacities.grown` reads)."""
    return dict(visible_anchors=jnp.sum(view.valid), dropped_anchors=view.overflow,
                active_gaussians=chosen.count, dropped_gaussians=chosen.overflow,
                pairs=out.num_pairs, dropped_pairs=out.overflow)


def render_model(anchors: AnchorState, nets: dict, camera: Camera, appearance_index, cfg: Config,
                 capacities: Capacities, banks: dict | None = None) -> tuple[RenderOutput, dict, dict]:
    """Decode the visible slots at ``camera`` and rasterise the active Gaussians (traceable).

    Returns:
      (RenderOutput with ``image`` [H, W, 3] — [H, W, 3+Q] when ``banks`` is given —, features
      {model: [H, W, D]} retrieved through the memory heads, or {} without ``banks``,
      :func:`work_metrics`).
    """
    out, features, view, chosen = render_view(anchors, nets, camera, appearance_index, cfg, capacities, banks)
    return out, features, work_metrics(view, chosen, out)


def render_view(anchors: AnchorState, nets: dict, camera: Camera, appearance_index, cfg: Config,
                capacities: Capacities, banks: dict | None = None):
    """:func:`render_model`'s pipeline, returning what it rendered from: ``(RenderOutput, features,
    VisibleSlots [S], ActiveSet [G_act])`` (:func:`cusgs_jax.render` reads the per-Gaussian meta off the last two)."""
    model = cfg.model
    view = visible_slots(anchors, camera, num_slots=capacities.visible_slots(anchors.capacity),
                         margin=model.frustum_margin)
    inputs = view_inputs(nets, *gather_visible(anchors, view), camera, appearance_index, model)
    gaussians, queries = decode_view_inputs(nets, inputs, cfg, queries=banks is not None)
    out, chosen = render_gaussians(gaussians, camera, cfg.splat,
                                   active_capacity=capacities.active_gaussians(anchors.capacity, model.n_offsets),
                                   pair_capacity=capacities.pairs(anchors.capacity, model.n_offsets),
                                   extra_channels=queries)
    features = {} if banks is None else retrieve(nets["memory"], banks, out.image[..., 3:], cfg.features)
    return out, features, view, chosen


def view_work(anchors: AnchorState, nets: dict, camera: Camera, appearance_index, cfg: Config) -> dict:
    """What one view needs, measured without any capacity (traceable; forward only, no sort).

    Every slot is decoded (S = A), every active Gaussian projected, and the tile pairs counted
    as the splatter bins them (:func:`cusgs_jax.splat.tiles.count_pairs`: the tiles each
    Gaussian's opacity-aware ellipse reaches).

    Returns:
      {"visible_anchors", "active_gaussians", "pairs"}: [] int32 each.
    """
    splat = cfg.splat
    g, view = decode_view(nets, anchors, camera, appearance_index, cfg.model, anchors.capacity)
    proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, camera.world_to_camera, camera.K,
                             camera.width, camera.height, antialiased=splat.antialiased, lens=camera.lens)
    grid = TileGrid(camera.width, camera.height, splat.tile_size)
    pairs = count_pairs(proj.means2d, proj.radii, proj.visible, grid,
                        *((proj.conics, proj.opacities) if splat.tiles == "ellipse" else ()))  # as the splatter bins
    return dict(visible_anchors=jnp.sum(view.valid).astype(jnp.int32),
                active_gaussians=jnp.sum(g.active).astype(jnp.int32),
                pairs=jnp.sum(pairs).astype(jnp.int32))


def make_render_fn(cfg: Config, capacities: Capacities | None = None, wrap=None) -> ExactRender:
    """``render(anchors, nets, camera, appearance_index) -> (rgb [H, W, 3] in [0, 1],)``.

    Meant for compacted anchors (:func:`cusgs_jax.model.anchors.compact`). The capacities
    (``capacities``, or, when None, sized by the first rendered view's need with headroom) grow
    whenever a view would drop visible anchors, active Gaussians or tile pairs, and the render is
    redone (:class:`~cusgs_jax.training.capacity.ExactRender`), so the image is always exact.
    """
    def build(capacities: Capacities):
        @jax.jit
        def render_rgb(anchors, nets, camera, appearance_index):
            out, _, work = render_model(anchors, nets, camera, appearance_index, cfg, capacities)
            return jnp.clip(out.image, 0.0, 1.0), work

        return render_rgb

    return ExactRender(build, capacities, cfg.model.n_offsets, fit=view_work_probe(cfg), **_wrapped(wrap))


def make_feature_render_fn(cfg: Config, capacities: Capacities | None = None, wrap=None) -> ExactRender:
    """``render(anchors, nets, camera, appearance_index, banks) -> (rgb [H,W,3], {model: [H,W,D]})``.

    Like :func:`make_render_fn`: capacities fitted and grown, never a truncated render.
    """
    def build(capacities: Capacities):
        @jax.jit
        def render_rgb_features(anchors, nets, camera, appearance_index, banks):
            out, features, work = render_model(anchors, nets, camera, appearance_index, cfg, capacities, banks)
            return jnp.clip(out.image[..., :3], 0.0, 1.0), features, work

        return render_rgb_features

    return ExactRender(build, capacities, cfg.model.n_offsets, fit=view_work_probe(cfg), **_wrapped(wrap))


def _wrapped(wrap) -> dict:
    """``ExactRender``'s ``wrap`` keyword when one is given (``wrap(jitted)``, e.g. :class:`cusgs_jax.app.ahead.Program`)."""
    return {} if wrap is None else dict(wrap=wrap)


@dataclasses.dataclass
class RgbOfFeatureRender:
    """``render(anchors, nets, camera, appearance_index) -> (rgb [H, W, 3],)`` from a feature render
    (:func:`make_feature_render_fn`) and the memory ``banks``: the RGB it composites in the same pass,
    so a run with feature models evaluates RGB and features with one compiled program.

    ``growths`` is 0: the feature render counts its own.
    """

    feature_render: ExactRender
    banks: dict
    growths: int = 0

    def __call__(self, anchors, nets, camera, appearance_index):
        return self.feature_render(anchors, nets, camera, appearance_index, self.banks)[:1]


def view_work_probe(cfg: Config):
    """``fit(anchors, nets, camera, appearance_index, *rest) -> needs`` (host ints; :func:`view_work`
    jitted), the ``fit`` of :class:`ExactRender`."""
    probe = jax.jit(lambda anchors, nets, camera, index: view_work(anchors, nets, camera, index, cfg))

    def fit(anchors, nets, camera, index, *rest):
        return {k: int(v) for k, v in jax.device_get(probe(anchors, nets, camera, index)).items()}

    return fit


def most_work(anchors: AnchorState, nets: dict, views, cfg: Config) -> dict:
    """The most any of ``views`` (pairs ``(camera, appearance_index)`` of one image size) needs of each
    capacity (:func:`view_work`): ``{"visible_anchors", "active_gaussians", "pairs"}`` as host ints.

    One jitted program walks the views (``lax.map``: one view's memory at a time) and one transfer
    brings the answer back — no per-view round trip.
    """
    needs = view_needs(anchors, nets, views, cfg)
    return {key: max(need[key] for need in needs) for key in needs[0]}


def view_needs(anchors: AnchorState, nets: dict, views, cfg: Config) -> list[dict]:
    """What each of ``views`` (pairs ``(camera, appearance_index)`` of one image size) needs (:func:`view_work`),
    in order: ``[{"visible_anchors", "active_gaussians", "pairs"}]`` as host ints (one program, one transfer)."""
    # stacked on the host and moved once (eager stacks would compile a program per shape)
    cameras = jax.device_put(jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]),
                                                    *[camera for camera, _ in views]))
    indices = jax.device_put(np.asarray([np.asarray(index) for _, index in views], np.int32))
    work = jax.device_get(_probe_views(anchors, nets, cameras, indices, cfg))
    return [{key: int(values[v]) for key, values in work.items()} for v in range(len(views))]


@functools.partial(jax.jit, static_argnames=("cfg",))
def _probe_views(anchors, nets, cameras, indices, cfg):
    """{"visible_anchors", "active_gaussians", "pairs"}: [V] int32, :func:`view_work` of each view."""
    return jax.lax.map(lambda view: view_work(anchors, nets, view[0], view[1], cfg), (cameras, indices))
