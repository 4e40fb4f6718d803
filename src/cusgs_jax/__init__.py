"""cusgs-jax: CUS-GS (compact unified structured Gaussian splatting) in JAX."""

from cusgs_jax.splat import RenderOutput, check_inputs, rasterize, rasterize_batch

__version__ = "0.1.0"
__all__ = ["RenderOutput", "check_inputs", "rasterize", "rasterize_batch"]
