"""Lens distortion inside the projection: rasterising through a distorted camera.

With ``data.undistort=lens`` the images are kept as captured and every Gaussian is projected
through the camera's own lens model instead of undistorting the images to a pinhole first (no
resampling blur, no crop, no invalid border). The projection stays EWA's local affine
approximation (Zwicker et al. 2002), with the lens in the chain rule: a camera point
``p = (x, y, z)`` maps to the pixel ``π(p) = f ⊙ D(x/z, y/z) + c``, so its 2D covariance is
``J Σ Jᵀ`` with ``J = diag(f) · ∂D/∂(u, v) · ∂(u, v)/∂p`` — the first-order treatment of distorted
cameras used by e.g. Fisheye-GS (Liao et al. 2024); gsplat's 3DGUT reaches the same cameras with
the unscented transform instead. It is exact for the centre and good while a Gaussian is small
against the scale on which the distortion changes.

Models, in COLMAP's parameterisation (``colmap/src/colmap/sensor/models.h``) with the normalised
undistorted coordinates ``(u, v) = (x/z, y/z)``, ``r² = u² + v²``:

* radial–tangential (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV without its rational part, and the
  two pinholes, with zeros):
  ``D(u, v) = (u·ρ + 2 p1 u v + p2 (r² + 2u²),  v·ρ + 2 p2 u v + p1 (r² + 2v²))``,
  ``ρ = 1 + k1 r² + k2 r⁴ + k3 r⁶``;
* fisheye (OPENCV_FISHEYE, equidistant): ``θ = atan r``,
  ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``, ``D(u, v) = (u, v) · θ_d / r``.

A polynomial lens is only a valid model near the image: far outside it the distorted radius stops
growing and folds back, so a point far outside the field of view could land inside the image. Each
lens therefore carries ``bounds``, a box of the undistorted plane (the image's own, widened where
the model is still one-to-one; :func:`cusgs_jax.data.lenses.lens_of_camera`): Gaussians whose
centre lies outside it are culled, and anchors outside it are not visible.

Shapes: G Gaussians (or points).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

__all__ = ["COEFFICIENTS", "Lens", "distort", "distort_with_jacobian", "inside_bounds"]

COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2")  # the order of Lens.coeffs


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lens:
    """The distortion of one camera (or, with leading axes, of a batch of cameras).

    Attributes:
      coeffs: [..., 6] float (k1, k2, k3, k4, p1, p2) in COLMAP's meaning (:data:`COEFFICIENTS`);
        radial–tangential lenses use k1–k3, p1, p2 (k4 = 0), fisheye lenses k1–k4 (p = 0).
      bounds: [..., 4] float (u_min, u_max, v_min, v_max): the box of normalised undistorted
        coordinates where the lens model is trusted (module docstring).
      fisheye: static; the equidistant fisheye model instead of the radial–tangential one.
    """

    coeffs: jax.Array
    bounds: jax.Array
    fisheye: bool = dataclasses.field(default=False, metadata=dict(static=True))

    @staticmethod
    def of_views(table, index) -> Lens:
        """The lenses of views ``index`` (an int, or an index array for a batch) of a per-view table
        with ``coeffs`` [V, 6], ``bounds`` [V, 4] and ``fisheye`` (e.g.
        :class:`cusgs_jax.data.lenses.SceneLens`)."""
        return Lens(jnp.asarray(table.coeffs[index], jnp.float32), jnp.asarray(table.bounds[index], jnp.float32),
                    bool(table.fisheye))


def _distort_point(coeffs: jax.Array, uv: jax.Array, fisheye: bool) -> jax.Array:
    """D(u, v) of one point: [2] → [2] (module docstring)."""
    k1, k2, k3, k4, p1, p2 = (coeffs[i] for i in range(6))
    u, v = uv[0], uv[1]
    r2 = u * u + v * v
    if fisheye:
        # θ_d / r with a Taylor branch at the axis, where atan(r)/r → 1 (both branches are
        # smooth, so the derivative through the `where` is finite; COLMAP uses D = identity there).
        small = r2 < 1e-8
        r = jnp.sqrt(jnp.where(small, 1.0, r2))
        theta = jnp.arctan(r)
        theta_over_r = jnp.where(small, 1.0 - r2 / 3.0, theta / r)
        t2 = jnp.where(small, r2, theta * theta)
        scale = theta_over_r * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        return jnp.stack([u * scale, v * scale])
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return jnp.stack([u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u),
                      v * radial + 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v)])


def distort(lens: Lens, uv: jax.Array) -> jax.Array:
    """Distorted normalised coordinates of ``uv`` [G, 2] through ``lens`` (one camera): [G, 2]."""
    return jax.vmap(lambda p: _distort_point(lens.coeffs, p, lens.fisheye))(uv)


def distort_with_jacobian(lens: Lens, uv: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(D(uv) [G, 2], ∂D/∂(u, v) [G, 2, 2]) through ``lens`` (one camera); both differentiable."""
    def one(p):
        return _distort_point(lens.coeffs, p, lens.fisheye)

    return jax.vmap(one)(uv), jax.vmap(jax.jacfwd(one))(uv)


def inside_bounds(lens: Lens, uv: jax.Array) -> jax.Array:
    """[G] bool: ``uv`` [G, 2] lies in the lens's trusted box (and is finite)."""
    b = lens.bounds
    return ((uv[:, 0] >= b[0]) & (uv[:, 0] <= b[1]) & (uv[:, 1] >= b[2]) & (uv[:, 1] <= b[3])
            & jnp.all(jnp.isfinite(uv), axis=-1))
