"""Real spherical harmonics → RGB, exactly as the standard 3DGS PLY means it (docs/rasterizer.md#spherical-harmonics).

``rgb = max(0, 0.5 + Σ_k c_k Y_k(dir))`` with graphdeco's ``utils/sh_utils.py``
``eval_sh`` constants and signs (the same as gsplat's ``eval_sh`` /
``spherical_harmonics``), degrees 0–3, and ``dir = normalize(mean − camera
centre)`` at the caller. Pure and jittable; differentiable in the coefficients
and the directions.

Naming (:mod:`cusgs_jax.types`): K = (d+1)² SH coefficients per colour channel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cusgs_jax.precision import HIGHEST

__all__ = ["SH_C0", "SH_C1", "SH_C2", "SH_C3", "MAX_SH_DEGREE", "num_sh_coeffs", "sh_basis", "sh_degree",
           "sh_to_rgb"]

# graphdeco utils/sh_utils.py (PlenOctrees' eval_sh), gsplat's eval_sh: identical values.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_coeffs(degree: int) -> int:
    """K = (degree + 1)² coefficients per channel."""
    return (int(degree) + 1) ** 2


def sh_degree(num_coeffs: int) -> int:
    """The degree d with (d+1)² = ``num_coeffs``; ValueError if there is none."""
    d = round(num_coeffs ** 0.5) - 1
    if d < 0 or (d + 1) ** 2 != num_coeffs:
        raise ValueError(f"{num_coeffs} SH coefficients per channel is not (d+1)² for an integer degree d ≥ 0")
    return d


def _normalize(dirs: jax.Array) -> jax.Array:
    # torch's F.normalize (as gsplat): x / max(‖x‖, 1e-12); finite gradient at 0.
    sq = jnp.sum(dirs * dirs, axis=-1, keepdims=True)
    return dirs / jnp.sqrt(jnp.maximum(sq, 1e-24))


def sh_basis(dirs: jax.Array, degree: int) -> jax.Array:
    """The real SH basis Y_k(dir) of graphdeco's ``eval_sh``.

    Args:
      dirs: [..., 3] directions (normalised here; any length > 0).
      degree: static SH degree d ∈ {0, 1, 2, 3}.
    Returns:
      [..., K] with K = (d+1)², in ``eval_sh``'s coefficient order (so that
      ``Σ_k c_k Y_k = basis @ c``; useful for least-squares SH fits).
    """
    if degree not in range(MAX_SH_DEGREE + 1):
        raise ValueError(f"SH degree must be 0, 1, 2 or 3, got {degree}")
    dirs = jnp.asarray(dirs)
    ones = jnp.ones(dirs.shape[:-1], dirs.dtype if jnp.issubdtype(dirs.dtype, jnp.floating) else jnp.float32)
    terms = [SH_C0 * ones]
    if degree >= 1:
        d = _normalize(dirs)
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        terms += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                  SH_C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [SH_C3[0] * y * (3.0 * xx - yy),
                  SH_C3[1] * xy * z,
                  SH_C3[2] * y * (4.0 * zz - xx - yy),
                  SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                  SH_C3[4] * x * (4.0 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy),
                  SH_C3[6] * x * (xx - 3.0 * yy)]
    return jnp.stack(terms, axis=-1)


def sh_to_rgb(coeffs: jax.Array, dirs: jax.Array, degree: int | None = None) -> jax.Array:
    """View-dependent colour of SH coefficients: ``max(0, 0.5 + Σ_k c_k Y_k(dir))`` per channel.

    Args:
      coeffs: [..., K, 3] coefficients, coefficient-major (``coeffs[..., 0, :]`` is
        the PLY's ``f_dc``), K = (d+1)² for d ≤ 3.
      dirs: [..., 3] view directions (mean − camera centre; normalised here),
        broadcastable against ``coeffs[..., 0, :]``.
      degree: static degree to evaluate (≤ the coefficients' degree; the higher
        coefficients are ignored, as gsplat's ``sh_degree`` during warm-up). None: all.
    Returns:
      [..., 3] RGB, clamped below at 0 (not above, as graphdeco and gsplat).
    """
    full = sh_degree(coeffs.shape[-2])
    degree = full if degree is None else int(degree)
    if not 0 <= degree <= full:
        raise ValueError(f"SH degree {degree} asked of coefficients of degree {full}")
    k = num_sh_coeffs(degree)
    basis = sh_basis(dirs, degree)
    rgb = 0.5 + jnp.einsum("...k,...kc->...c", basis, coeffs[..., :k, :], precision=HIGHEST)
    return jnp.maximum(rgb, 0.0)
