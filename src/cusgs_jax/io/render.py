"""Rendering a :class:`~cusgs_jax.io.ply.SplatModel` (a standard 3DGS PLY) with our splatter.

Colours are evaluated per Gaussian and view as graphdeco's renderer and gsplat
do: ``rgb = max(0, 0.5 + Σ_k c_k Y_k(normalize(mean − camera centre)))``
(:func:`cusgs_jax.splat.sh.sh_to_rgb`, docs/rasterizer.md#spherical-harmonics), then
:func:`cusgs_jax.splat.rasterize` composites them (docs/rasterizer.md#compositing; classic mode
unless ``antialiased=True`` is passed, as the Inria PLYs are trained).

Naming (:mod:`cusgs_jax.types`): G Gaussians, K SH coefficients, H×W image.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import SplatConfig
from cusgs_jax.errors import UserError
from cusgs_jax.io.ply import SplatModel
from cusgs_jax.splat import Compositor, RenderOutput, rasterize
from cusgs_jax.splat.sh import MAX_SH_DEGREE, sh_to_rgb
from cusgs_jax.training.capacity import grown_pairs_per_gaussian, max_pairs
from cusgs_jax.types import Camera

__all__ = ["recentre_splats", "render_splats", "render_splats_exact", "scene_camera", "splat_colors"]


def _degree(model: SplatModel, sh_degree: int | None) -> int:
    full = model.sh_degree
    degree = min(full, MAX_SH_DEGREE) if sh_degree is None else int(sh_degree)
    if sh_degree is None and full > MAX_SH_DEGREE:
        raise UserError(f"the model has SH degree {full}; the renderer evaluates degrees 0–{MAX_SH_DEGREE}: "
                        f"pass sh_degree ≤ {MAX_SH_DEGREE} to render with the lower coefficients only")
    if not 0 <= degree <= min(full, MAX_SH_DEGREE):
        raise UserError(f"sh_degree {sh_degree} must be in 0..{min(full, MAX_SH_DEGREE)} for a model of degree {full}")
    return degree


def _require_model(model, function: str) -> None:
    """TypeError naming ``model`` unless it is a :class:`SplatModel` (a pytree: also true under jit)."""
    if not isinstance(model, SplatModel):
        raise TypeError(f"{function}(): model must be a cusgs_jax.io.SplatModel (e.g. from cusgs_jax.io.read_ply "
                        f"or a run's model), got {type(model).__name__}")


def _require_camera(camera, function: str) -> None:
    if not isinstance(camera, Camera):
        raise TypeError(f"{function}(): camera must be a cusgs_jax.types.Camera (e.g. from "
                        f"cusgs_jax.io.scene_camera), got {type(camera).__name__}")


def splat_colors(model: SplatModel, camera_center: jax.Array, sh_degree: int | None = None) -> jax.Array:
    """[G, 3] RGB of every Gaussian seen from ``camera_center`` [3] (dirs = mean − centre, as gsplat)."""
    _require_model(model, "splat_colors")
    degree = _degree(model, sh_degree)
    sh = jnp.asarray(model.sh)[:, : (degree + 1) ** 2]
    return sh_to_rgb(sh, jnp.asarray(model.means) - camera_center)


def render_splats(model: SplatModel, camera: Camera, *, background, sh_degree: int | None = None,
                  **rasterize_kwargs) -> RenderOutput:
    """Render a standard-PLY model at ``camera``: pure and jittable (``sh_degree`` static).

    Args:
      model: G Gaussians (quats normalised, scales exp'd, opacities sigmoid'ed here).
      camera: :class:`cusgs_jax.types.Camera` in the model's world frame.
      background: [3] RGB behind the Gaussians.
      sh_degree: evaluate SH up to this degree (None: the model's, at most 3).
      rasterize_kwargs: passed to :func:`cusgs_jax.splat.rasterize`; ``tile_size``
        and ``compositor`` (splat.backend, splat.chunk_size) default to :class:`cusgs_jax.config.SplatConfig`'s,
        ``max_pairs`` to the training default capacity
        (:func:`cusgs_jax.training.capacity.max_pairs`).
    Returns:
      :class:`cusgs_jax.splat.RenderOutput`; ``image`` [H, W, 3] is not clipped.
      ``overflow > 0`` means tile pairs were dropped (see :func:`render_splats_exact`).
    Raises:
      TypeError: ``model`` not a :class:`~cusgs_jax.io.ply.SplatModel` or ``camera`` not a
        :class:`~cusgs_jax.types.Camera`.
    """
    _require_model(model, "render_splats")
    _require_camera(camera, "render_splats")
    defaults = SplatConfig()
    kwargs = dict(tile_size=defaults.tile_size, compositor=Compositor(defaults.backend, defaults.chunk_size),
                  max_pairs=max_pairs(defaults.max_pairs_per_gaussian, model.num_gaussians))
    kwargs.update(rasterize_kwargs)
    colors = splat_colors(model, camera.center, sh_degree)
    return rasterize(jnp.asarray(model.means), jnp.asarray(model.quats), model.scales, model.opacities, colors,
                     camera.world_to_camera, camera.K, camera.width, camera.height,
                     background=jnp.asarray(background, colors.dtype), lens=camera.lens, **kwargs)


@functools.partial(jax.jit, static_argnames=("sh_degree", "options"))
def _render_jit(model, camera, background, sh_degree, options):
    return render_splats(model, camera, background=background, sh_degree=sh_degree, **dict(options))


def render_splats_exact(model: SplatModel, camera: Camera, *, background, sh_degree: int | None = None,
                        pairs_per_gaussian: float | None = None, **rasterize_kwargs) -> tuple[RenderOutput, float]:
    """:func:`render_splats`, jitted, never truncated: re-rendered with a grown pair capacity on overflow.

    Host-side (not jittable). ``pairs_per_gaussian`` is the first tile-pair
    capacity per Gaussian (default ``SplatConfig().max_pairs_per_gaussian``).
    Returns ``(output, pairs_per_gaussian)``: pass the latter to the next call
    so that later views start at the grown capacity (one compile per capacity).
    """
    if "max_pairs" in rasterize_kwargs:
        raise TypeError("render_splats_exact chooses max_pairs itself; pass pairs_per_gaussian instead")
    _require_model(model, "render_splats_exact")
    _require_camera(camera, "render_splats_exact")
    degree = _degree(model, sh_degree)
    per = SplatConfig().max_pairs_per_gaussian if pairs_per_gaussian is None else float(pairs_per_gaussian)
    num = model.num_gaussians
    while True:
        options = tuple(sorted(dict(rasterize_kwargs, max_pairs=max_pairs(per, num)).items()))
        out = _render_jit(model, camera, jnp.asarray(background, jnp.float32), degree, options)
        if int(out.overflow) == 0:
            return out, per
        per = grown_pairs_per_gaussian(per, int(out.num_pairs) + int(out.overflow), num)


def recentre_splats(model: SplatModel, centre) -> tuple[SplatModel, np.ndarray]:
    """(the model moved by −``centre``, ``centre`` [3] float64): float32 keeps a far-off scene's detail.

    Rendering is translation-invariant (view directions are mean − camera centre), so moving the
    Gaussians and the cameras (:func:`scene_camera`) together changes nothing else. ``centre`` is
    usually the scene's mean camera centre; the means are shifted in float64.
    """
    centre = np.asarray(centre, np.float64).reshape(3)
    means = (np.asarray(model.means, np.float64) - centre).astype(np.float32)
    return dataclasses.replace(model, means=means), centre


def scene_camera(scene, view: int, shift) -> Camera:
    """The scene's camera ``view`` in the frame moved by −``shift`` [3]: x_cam = R(x + shift) + t (float64).

    ``scene``: a :class:`~cusgs_jax.data.scene_data.SceneData` (``viewmats`` [V, 4, 4], ``Ks`` [V, 3, 3],
    ``lens``: the view's lens is kept, so a ``data.undistort=lens`` scene renders through it).
    """
    viewmat = np.array(scene.viewmats[view], np.float64)
    viewmat[:3, 3] += viewmat[:3, :3] @ np.asarray(shift, np.float64)
    camera = Camera.of_scene(scene, view)
    return dataclasses.replace(camera, K=jnp.asarray(scene.Ks[view], jnp.float32),
                               world_to_camera=jnp.asarray(viewmat, jnp.float32))
