"""Projection of 3D Gaussians to screen space (gsplat 1.5.3 conventions).

Shapes: G Gaussians. All functions are pure, differentiable with respect to the
floating-point inputs, and safe on degenerate input: culled Gaussians get finite
placeholder values and exactly zero gradient.

Conventions (docs/rasterizer.md#projection):
  * quaternions are ``wxyz`` and normalised here; covariance ``Σ = R S² Rᵀ``;
  * ``viewmat`` is world→camera with OpenCV axes (+z forward, +y down);
  * EWA Jacobian with ``x/z``, ``y/z`` clamped to the frustum widened by 30 %;
  * low-pass ``Σ' = Σ + eps2d·I``; the antialiased mode multiplies the opacity
    by ``sqrt(det Σ / det Σ')``;
  * conic ``[Σ'11, −Σ'01, Σ'00] / det Σ'``;
  * footprint ``ceil(extend · sqrt(diag Σ'))`` with the opacity-aware
    ``extend = min(3.33, sqrt(2 ln(255 o)))``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from cusgs_jax.splat.lens import Lens, distort_with_jacobian, inside_bounds
from cusgs_jax.precision import HIGHEST

ALPHA_THRESHOLD = 1.0 / 255.0


class Projection(NamedTuple):
    """Screen-space Gaussians.

    Attributes:
      means2d: [G, 2] pixel coordinates (x right, y down; pixel (i, j) is
        sampled at (j + 0.5, i + 0.5)).
      conics: [G, 3] inverse 2D covariance ``(a, b, c)`` so that
        ``σ = ½(a dx² + c dy²) + b dx dy``.
      depths: [G] camera-space z.
      opacities: [G] opacity used for compositing (compensated in antialiased
        mode).
      radii: [G, 2] float footprint half-extent in pixels, already ``ceil``-ed
        (0 when culled; may be astronomically large near the near plane).
      visible: [G] bool, passes near/far, determinant, opacity and on-screen
        tests.
    """

    means2d: jax.Array
    conics: jax.Array
    depths: jax.Array
    opacities: jax.Array
    radii: jax.Array
    visible: jax.Array


def _safe_sqrt(x: jax.Array) -> jax.Array:
    """sqrt with a finite (zero) gradient at and below 0."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def normalize_quats(quats: jax.Array) -> jax.Array:
    """Unit quaternions from arbitrary ones, robust to zero/tiny/huge norms.

    The quaternion is first divided by its largest absolute component so that
    squaring can neither underflow (norm 1e-20) nor overflow (norm 1e20); a
    zero (or non-finite) quaternion becomes the identity.

    Args:
      quats: [..., 4] wxyz.
    Returns:
      [..., 4] wxyz of unit norm.
    """
    # normalize(q / s) = normalize(q) for any s > 0, so holding s constant in
    # the derivative is exact, and it avoids the 1/s² that underflows at 1e-20.
    largest = jax.lax.stop_gradient(jnp.max(jnp.abs(quats), axis=-1, keepdims=True))
    ok = (largest > 0) & jnp.isfinite(largest)
    identity = jnp.zeros_like(quats).at[..., 0].set(1.0)
    scaled = jnp.where(ok, quats / jnp.where(ok, largest, 1.0), identity)
    return scaled / jnp.linalg.norm(scaled, axis=-1, keepdims=True)


def quats_to_rotmats(quats: jax.Array) -> jax.Array:
    """Rotation matrices of unit wxyz quaternions.

    Args:
      quats: [..., 4] unit wxyz.
    Returns:
      [..., 3, 3].
    """
    w, x, y, z = jnp.moveaxis(quats, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


# --- compensated world→camera transform -------------------------------------
# Scene coordinates far from the origin (1e4) make `R p + t` cancel
# catastrophically in float32: each product carries an error of ulp(1e4) ≈ 1e-3
# that survives the subtraction of t. Re-centring on the camera does not help
# because the camera centre −Rᵀt carries the same rounding. Instead the dot
# product is evaluated with error-free transformations (Ogita, Rump & Oishi,
# "Accurate sum and dot product", 2005, algorithm Dot2), which gives the result
# as if computed in twice the working precision; it costs ~60 flops per
# Gaussian, nothing next to rasterisation.


def _two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _split(a):
    factor = 4097.0 if a.dtype == jnp.float32 else 134217729.0  # 2^ceil(p/2) + 1
    c = factor * a
    hi = c - (c - a)
    return hi, a - hi


def _two_prod(a, b):
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@jax.custom_jvp
def world_to_camera(means: jax.Array, viewmat: jax.Array) -> jax.Array:
    """Camera-space points ``R p + t`` evaluated in compensated arithmetic.

    Args:
      means: [G, 3] world points.
      viewmat: [4, 4] world→camera.
    Returns:
      [G, 3] camera-space points.
    """
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    total = jnp.broadcast_to(trans, means.shape)
    compensation = jnp.zeros_like(means)
    for j in range(3):
        prod, prod_err = _two_prod(rot[None, :, j], means[:, j : j + 1])
        total, sum_err = _two_sum(total, prod)
        compensation = compensation + (prod_err + sum_err)
    return total + compensation


@world_to_camera.defjvp
def _world_to_camera_jvp(primals, tangents):
    means, viewmat = primals
    d_means, d_viewmat = tangents
    out = world_to_camera(means, viewmat)
    d_out = (
        jnp.matmul(d_means, viewmat[:3, :3].T, precision=HIGHEST)
        + jnp.matmul(means, d_viewmat[:3, :3].T, precision=HIGHEST)
        + d_viewmat[:3, 3]
    )
    return out, d_out


def project_gaussians(
    means: jax.Array,
    quats: jax.Array,
    scales: jax.Array,
    opacities: jax.Array,
    viewmat: jax.Array,
    K: jax.Array,
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    antialiased: bool = False,
    lens: Lens | None = None,
) -> Projection:
    """Project Gaussians to the image plane (gsplat ``fully_fused_projection``).

    Args:
      means: [G, 3] world centres.
      quats: [G, 4] wxyz rotations (any norm).
      scales: [G, 3] linear standard deviations.
      opacities: [G] in [0, 1].
      viewmat: [4, 4] world→camera, OpenCV axes.
      K: [3, 3] pinhole intrinsics.
      width, height: static image size in pixels.
      near, far: depth culling planes (camera z).
      eps2d: low-pass variance added to the 2D covariance.
      antialiased: multiply opacities by ``sqrt(det Σ / det Σ')``.
      lens: the camera's distortion (:mod:`cusgs_jax.splat.lens`), or None for a pinhole. With a
        lens the centre goes through the lens model and the EWA Jacobian through its derivative
        (no frustum clamp: Gaussians centred outside the lens's trusted box are culled instead).
    Returns:
      A :class:`Projection`.
    """
    dtype = means.dtype
    p_cam = world_to_camera(means, viewmat)
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    in_depth = (z >= near) & (z <= far)
    z_safe = jnp.where(in_depth, z, 1.0)

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if lens is None:
        jac, means2d = _pinhole_jacobian(x, y, z_safe, fx, fy, cx, cy, width, height)
    else:
        jac, means2d, trusted = _lens_jacobian(lens, x, y, z_safe, fx, fy, cx, cy)
        in_depth = in_depth & trusted

    # Σ2d = A Aᵀ with A = J R_view R_q S  (2×3). Cauchy–Binet gives det(A Aᵀ)
    # as the sum of squared 2×2 minors of A: non-negative and free of the
    # catastrophic cancellation of `a c − b²` for needle-like covariances.
    rot = quats_to_rotmats(normalize_quats(quats))
    world_to_cam_rot = viewmat[:3, :3].astype(dtype)
    factor = jnp.einsum("ij,gjk->gik", world_to_cam_rot, rot, precision=HIGHEST) * scales[:, None, :]
    proj = jnp.einsum("gij,gjk->gik", jac, factor, precision=HIGHEST)  # [G, 2, 3]
    cov_a = jnp.sum(proj[:, 0] * proj[:, 0], axis=-1)
    cov_b = jnp.sum(proj[:, 0] * proj[:, 1], axis=-1)
    cov_c = jnp.sum(proj[:, 1] * proj[:, 1], axis=-1)
    minors = (
        proj[:, 0, [0, 0, 1]] * proj[:, 1, [1, 2, 2]]
        - proj[:, 0, [1, 2, 2]] * proj[:, 1, [0, 0, 1]]
    )
    det_orig = jnp.sum(minors * minors, axis=-1)
    det = det_orig + eps2d * (cov_a + cov_c) + eps2d * eps2d
    cov_a = cov_a + eps2d
    cov_c = cov_c + eps2d
    det_ok = det > 0
    det_safe = jnp.where(det_ok, det, 1.0)
    conics = jnp.stack([cov_c, -cov_b, cov_a], axis=-1) / det_safe[:, None]

    if antialiased:
        opacities = opacities * _safe_sqrt(det_orig / det_safe)

    # Footprint (not differentiable): opacity-aware 3.33-sigma box.
    o_ng = jax.lax.stop_gradient(opacities)
    bright = o_ng >= ALPHA_THRESHOLD
    extend = jnp.minimum(
        3.33, jnp.sqrt(2.0 * jnp.log(jnp.maximum(o_ng, ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
    )
    sd = jax.lax.stop_gradient(jnp.stack([cov_a, cov_c], axis=-1))
    radius = jnp.ceil(extend[:, None] * jnp.sqrt(jnp.maximum(sd, 0.0)))
    m2 = jax.lax.stop_gradient(means2d)
    on_screen = (
        (m2[:, 0] + radius[:, 0] > 0)
        & (m2[:, 0] - radius[:, 0] < width)
        & (m2[:, 1] + radius[:, 1] > 0)
        & (m2[:, 1] - radius[:, 1] < height)
    )
    visible = (
        in_depth
        & det_ok
        & bright
        & ((radius[:, 0] > 0) | (radius[:, 1] > 0))
        & on_screen
        & jnp.all(jnp.isfinite(m2), axis=-1)
    )
    radii = jnp.where(visible[:, None], radius, 0.0)

    means2d = jnp.where(visible[:, None], means2d, 0.0)
    conics = jnp.where(visible[:, None], conics, 0.0)
    opacities = jnp.where(visible, opacities, 0.0)
    return Projection(means2d, conics, z, opacities, radii, visible)


def _pinhole_jacobian(x, y, z_safe, fx, fy, cx, cy, width, height):
    """(EWA Jacobian [G, 2, 3] with x/z, y/z clamped to the frustum widened by 30 %, pixel centres [G, 2])."""
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    rz = 1.0 / z_safe
    tx = z_safe * jnp.clip(x * rz, -lim_x_neg, lim_x_pos)
    ty = z_safe * jnp.clip(y * rz, -lim_y_neg, lim_y_pos)
    zeros = jnp.zeros_like(rz)
    jac = jnp.stack(
        [
            jnp.stack([fx * rz, zeros, -fx * tx * rz * rz], axis=-1),
            jnp.stack([zeros, fy * rz, -fy * ty * rz * rz], axis=-1),
        ],
        axis=-2,
    )  # [G, 2, 3]
    return jac, jnp.stack([fx * x * rz + cx, fy * y * rz + cy], axis=-1)


def _lens_jacobian(lens: Lens, x, y, z_safe, fx, fy, cx, cy):
    """(Jacobian of π(p) = f ⊙ D(x/z, y/z) + c [G, 2, 3], pixel centres [G, 2], [G] bool centre in the
    lens's trusted box) — :mod:`cusgs_jax.splat.lens`. Untrusted centres get the axis as a finite
    placeholder (they are culled, so their gradient is zero)."""
    rz = 1.0 / z_safe
    uv = jnp.stack([x * rz, y * rz], axis=-1)
    trusted = inside_bounds(lens, uv)
    uv = jnp.where(trusted[:, None], uv, 0.0)
    distorted, d_lens = distort_with_jacobian(lens, uv)  # [G, 2], [G, 2, 2]
    zeros = jnp.zeros_like(rz)
    d_persp = jnp.stack([jnp.stack([rz, zeros, -uv[:, 0] * rz], axis=-1),
                         jnp.stack([zeros, rz, -uv[:, 1] * rz], axis=-1)], axis=-2)  # ∂(u, v)/∂p [G, 2, 3]
    focal = jnp.stack([fx, fy])
    jac = focal[None, :, None] * jnp.einsum("gij,gjk->gik", d_lens, d_persp, precision=HIGHEST)
    return jac, focal * distorted + jnp.stack([cx, cy]), trusted
