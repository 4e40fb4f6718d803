"""Explicit Gaussians as the standard 3DGS files store them: what baking makes and the PLY and SPZ writers take.

Naming (:mod:`cusgs_jax.types`): G Gaussians, K = (d+1)² spherical-harmonic coefficients of degree d.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SplatModel:
    """Gaussians as the standard PLY stores them (pre-activation values), float32.

    Attributes:
      means: [G, 3] world centres (``x y z``).
      quats: [G, 4] wxyz rotations as stored (``rot_0..3``, unnormalised).
      log_scales: [G, 3] log standard deviations (``scale_0..2``).
      opacity_logits: [G] (``opacity``; the opacity is its sigmoid).
      sh: [G, K, 3] SH coefficients, coefficient-major: ``sh[:, 0, :]`` is ``f_dc``.
    """

    means: jax.Array
    quats: jax.Array
    log_scales: jax.Array
    opacity_logits: jax.Array
    sh: jax.Array

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """d with K = (d+1)²."""
        return int(round(self.sh.shape[-2] ** 0.5)) - 1

    @property
    def scales(self) -> jax.Array:
        """[G, 3] linear standard deviations, exp(log_scales)."""
        return jnp.exp(self.log_scales)

    @property
    def opacities(self) -> jax.Array:
        """[G] opacities in (0, 1), sigmoid(opacity_logits)."""
        return jax.nn.sigmoid(self.opacity_logits)
