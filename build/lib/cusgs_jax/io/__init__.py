"""Models that leave the project: the standard 3DGS PLY in and out, and rendering one (DESIGN.md §7)."""

from cusgs_jax.io.ply import PlyError, SplatModel, ply_property_names, read_ply, write_ply
from cusgs_jax.io.render import render_splats, render_splats_exact, splat_colors

__all__ = ["PlyError", "SplatModel", "ply_property_names", "read_ply", "render_splats", "render_splats_exact",
           "splat_colors", "write_ply"]
