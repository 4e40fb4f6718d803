"""Models that leave the project: the standard 3DGS PLY in and out (SPZ in :mod:`cusgs_jax.io.spz`), rendering one
and refining one (docs/formats.md#standard-3dgs-ply); a trained run folder read back (:mod:`cusgs_jax.io.load_run`)."""

from cusgs_jax.io.ply import PlyError, SplatModel, ply_property_names, read_ply, write_ply
from cusgs_jax.io.refine import heldout_psnr, make_refine_step, refine_splats
from cusgs_jax.io.render import recentre_splats, render_splats, render_splats_exact, scene_camera, splat_colors

__all__ = ["PlyError", "SplatModel", "heldout_psnr", "make_refine_step", "ply_property_names", "read_ply",
           "recentre_splats", "refine_splats", "render_splats", "render_splats_exact", "scene_camera",
           "splat_colors", "write_ply"]
