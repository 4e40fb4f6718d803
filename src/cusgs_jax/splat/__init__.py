"""Differentiable tile-based Gaussian splatting (gsplat 1.5.3 conventions).

Public API: :func:`rasterize`, :func:`rasterize_batch`, their jitted forms :data:`rasterize_jit` and
:data:`rasterize_batch_jit` (``jax.jit`` with :data:`RASTERIZE_STATIC_ARGNAMES`), :func:`check_inputs`,
:class:`RenderOutput`, and the stage functions they are built from;
:func:`sh_to_rgb` / :func:`sh_basis` (spherical harmonics as the standard 3DGS PLY means them).
"""

from cusgs_jax.splat.composite import Composite, composite_tiles
from cusgs_jax.splat.project import Projection, normalize_quats, project_gaussians, quats_to_rotmats
from cusgs_jax.splat.render import (
    RASTERIZE_STATIC_ARGNAMES,
    Compositor,
    RenderOutput,
    SparseChannels,
    check_inputs,
    check_values,
    default_max_pairs,
    rasterize,
    rasterize_batch,
    rasterize_batch_jit,
    rasterize_jit,
)
from cusgs_jax.splat.sh import sh_basis, sh_to_rgb
from cusgs_jax.splat.tiles import TileGrid, TileIntersections, intersect_tiles

__all__ = [
    "RASTERIZE_STATIC_ARGNAMES", "Composite", "Compositor", "Projection", "RenderOutput", "SparseChannels", "TileGrid",
    "TileIntersections", "check_inputs", "check_values", "composite_tiles", "default_max_pairs", "intersect_tiles",
    "normalize_quats", "project_gaussians", "quats_to_rotmats", "rasterize", "rasterize_batch",
    "rasterize_batch_jit", "rasterize_jit", "sh_basis", "sh_to_rgb",
]
