"""Slow float64 NumPy reference rasteriser for 3D Gaussian Splatting (test oracle).

This module is used only by the test-suite, as an oracle for the fast JAX
rasteriser.  It follows the conventions of gsplat 1.5.3 (EWA projection with
the ``persp_proj`` Jacobian clamp, ``eps2d`` low-pass filter, optional
anti-aliasing compensation, 0.999 alpha clamp, 1/255 alpha threshold and
transmittance termination at 1e-4) but is written for clarity, not speed:

* Step 1 (:func:`project_reference`) projects every Gaussian independently,
  vectorised over Gaussians with plain NumPy.
* Step 2 (:func:`rasterize_reference`) composites front to back.  The loop runs
  over Gaussians in depth order in Python and is vectorised over pixels, with
  a per-pixel ``done`` mask that reproduces the per-pixel ``break`` exactly.

Unlike gsplat there are no tiles: every Gaussian that passes the near/far and
``det > 0`` tests is considered at every pixel ("composite everything in depth
order").  The radius / off-screen test only decides the returned ``radii`` and
``visible`` arrays; outside the radius box the alpha is below 1/255 anyway.

Everything is computed in float64.  No JAX is imported here.
"""

from __future__ import annotations

import numpy as np

ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
MAX_EXTEND = 3.33


def normalize_quats_reference(quats):
    """Robustly normalise wxyz quaternions.

    Args:
        quats: [G, 4] quaternions (w, x, y, z), any scale.

    Returns:
        [G, 4] float64 unit quaternions.  Rows that are all zero or not finite
        become the identity (1, 0, 0, 0).  Otherwise each row is first divided by
        its largest absolute component (so tiny or huge inputs do not
        under/overflow) and then by its norm.
    """
    q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
    out = np.zeros_like(q)
    out[:, 0] = 1.0
    for g in range(q.shape[0]):
        s = np.max(np.abs(q[g]))
        if not (np.isfinite(s) and s > 0.0):
            continue
        qs = q[g] / s
        n = np.sqrt(np.sum(qs * qs))
        if not (np.isfinite(n) and n > 0.0):
            continue
        out[g] = qs / n
    return out


def quat_to_rotmat_reference(quats):
    """Rotation matrices from wxyz quaternions (normalised first).

    Args:
        quats: [G, 4] quaternions (w, x, y, z), need not be normalised.

    Returns:
        [G, 3, 3] float64 rotation matrices.
    """
    q = normalize_quats_reference(quats)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((q.shape[0], 3, 3), dtype=np.float64)
    R[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[:, 0, 1] = 2.0 * (x * y - w * z)
    R[:, 0, 2] = 2.0 * (x * z + w * y)
    R[:, 1, 0] = 2.0 * (x * y + w * z)
    R[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[:, 1, 2] = 2.0 * (y * z - w * x)
    R[:, 2, 0] = 2.0 * (x * z - w * y)
    R[:, 2, 1] = 2.0 * (y * z + w * x)
    R[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def distort_reference(coeffs, fisheye, uv):
    """COLMAP's lens models (cusgs_jax.splat.lens) and their analytic Jacobian, float64.

    Args:
        coeffs: [6] (k1, k2, k3, k4, p1, p2).
        fisheye: the equidistant fisheye model instead of the radial-tangential one.
        uv: [G, 2] normalised undistorted coordinates (x/z, y/z); r > 0 for the fisheye.
    Returns:
        (distorted [G, 2], Jacobian d distorted / d uv [G, 2, 2]).
    """
    k1, k2, k3, k4, p1, p2 = (float(c) for c in np.asarray(coeffs, np.float64))
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    u, v = uv[:, 0], uv[:, 1]
    r2 = u * u + v * v
    jac = np.zeros((len(uv), 2, 2))
    if fisheye:
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        poly = 1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4
        dpoly = k1 + 2 * k2 * t2 + 3 * k3 * t2**2 + 4 * k4 * t2**3  # d poly / d theta^2
        s = theta * poly / r
        ds_dr = (poly + 2 * t2 * dpoly) / (1 + r2) / r - theta * poly / r2
        out = np.stack([u * s, v * s], -1)
        jac[:, 0, 0] = s + u * u / r * ds_dr
        jac[:, 0, 1] = jac[:, 1, 0] = u * v / r * ds_dr
        jac[:, 1, 1] = s + v * v / r * ds_dr
        return out, jac
    rho = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    drho = k1 + 2 * k2 * r2 + 3 * k3 * r2**2  # d rho / d r^2
    out = np.stack([u * rho + 2 * p1 * u * v + p2 * (r2 + 2 * u * u),
                    v * rho + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)], -1)
    jac[:, 0, 0] = rho + 2 * u * u * drho + 2 * p1 * v + 6 * p2 * u
    jac[:, 0, 1] = 2 * u * v * drho + 2 * p1 * u + 2 * p2 * v
    jac[:, 1, 0] = 2 * u * v * drho + 2 * p2 * v + 2 * p1 * u
    jac[:, 1, 1] = rho + 2 * v * v * drho + 2 * p2 * u + 6 * p1 * v
    return out, jac


def project_reference(means, quats, scales, opacities, viewmat, K, width, height, *,
                      near=0.01, far=1e10, antialiased=False, eps2d=0.3, lens=None):
    """Step 1: project every Gaussian to the image plane (gsplat 1.5.3 conventions).

    Args:
        means: [G, 3] world-space centres.
        quats: [G, 4] rotations as wxyz quaternions (need not be normalised).
        scales: [G, 3] linear standard deviations along the local axes.
        opacities: [G] opacities in [0, 1].
        viewmat: [4, 4] world-to-camera matrix (OpenCV axes: +x right, +y down,
            +z forward).
        K: [3, 3] pinhole intrinsics.
        width, height: image size in pixels (ints).
        near, far: depth clipping planes (camera z).
        antialiased: if True, scale opacity by sqrt(det_orig / det).
        eps2d: isotropic low-pass term added to the 2D covariance.
        lens: None (pinhole), or (coeffs [6], bounds [4], fisheye) of a distorted camera: the
            centre goes through distort_reference, the Jacobian through its derivative (no clamp),
            and centres whose x/z, y/z lie outside bounds (u0, u1, v0, v1) are culled.

    Returns:
        dict with
            means2d [G, 2] float64 pixel coordinates (x, y),
            conics [G, 3] float64 (a, b, c) of the inverse 2D covariance
                [[a, b], [b, c]],
            cov2d [G, 2, 2] float64 low-passed 2D covariance,
            depths [G] float64 camera z,
            radii [G, 2] int64 (radius_x, radius_y), (0, 0) when not visible,
            visible [G] bool,
            opacities_eff [G] float64 opacity used for compositing,
            compensation [G] float64 sqrt(max(0, det_orig / det)),
            compositable [G] bool: passed near/far and det > 0 (these are the
                Gaussians step 2 composites; independent of the radius test).
        Entries of non-compositable Gaussians are zero.
    """
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    scales = np.asarray(scales, dtype=np.float64).reshape(-1, 3)
    opacities = np.asarray(opacities, dtype=np.float64).reshape(-1)
    viewmat = np.asarray(viewmat, dtype=np.float64).reshape(4, 4)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    G = means.shape[0]

    # World covariance  Sigma = R S^2 R^T.                               [G,3,3]
    R = quat_to_rotmat_reference(quats)
    M = R * scales[:, None, :]                    # R @ diag(s)
    cov_world = M @ np.swapaxes(M, 1, 2)

    # Camera space.                                                      [G,3]
    Rv = viewmat[:3, :3]
    t = viewmat[:3, 3]
    p_cam = means @ Rv.T + t
    cov_cam = Rv[None] @ cov_world @ Rv.T[None]   # [G,3,3]
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]

    in_range = (z >= near) & (z <= far)
    # Avoid division warnings for culled Gaussians; their outputs are zeroed.
    z_safe = np.where(in_range, z, 1.0)

    # Perspective Jacobian with gsplat's persp_proj clamp.
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * np.minimum(lim_x_pos, np.maximum(-lim_x_neg, x / z_safe))
    ty = z_safe * np.minimum(lim_y_pos, np.maximum(-lim_y_neg, y / z_safe))

    J = np.zeros((G, 2, 3), dtype=np.float64)
    J[:, 0, 0] = fx / z_safe
    J[:, 0, 2] = -fx * tx / (z_safe * z_safe)
    J[:, 1, 1] = fy / z_safe
    J[:, 1, 2] = -fy * ty / (z_safe * z_safe)
    means2d = np.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], axis=-1)
    if lens is not None:
        coeffs, bounds, fisheye = lens
        u, v = x / z_safe, y / z_safe
        trusted = (u >= bounds[0]) & (u <= bounds[1]) & (v >= bounds[2]) & (v <= bounds[3])
        in_range = in_range & trusted
        uv = np.where(in_range[:, None], np.stack([u, v], -1), 0.5)
        distorted, d_lens = distort_reference(coeffs, fisheye, uv)
        d_persp = np.zeros((G, 2, 3))
        d_persp[:, 0, 0] = d_persp[:, 1, 1] = 1 / z_safe
        d_persp[:, 0, 2], d_persp[:, 1, 2] = -uv[:, 0] / z_safe, -uv[:, 1] / z_safe
        J = np.array([fx, fy])[None, :, None] * (d_lens @ d_persp)
        means2d = distorted * [fx, fy] + [cx, cy]
    cov2d = J @ cov_cam @ np.swapaxes(J, 1, 2)    # [G,2,2]

    # Low-pass filter (+ eps2d * I) and anti-aliasing compensation.
    det_orig = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    cov2d[:, 0, 0] += eps2d
    cov2d[:, 1, 1] += eps2d
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    compositable = in_range & (det > 0)
    det_safe = np.where(compositable, det, 1.0)
    compensation = np.sqrt(np.maximum(0.0, det_orig / det_safe))
    opacities_eff = opacities * compensation if antialiased else opacities.copy()

    conics = np.stack([cov2d[:, 1, 1] / det_safe,
                       -cov2d[:, 0, 1] / det_safe,
                       cov2d[:, 0, 0] / det_safe], axis=-1)

    # Radius (only for radii / visible; does not affect the image).
    visible = compositable & (opacities_eff >= ALPHA_THRESHOLD)
    ratio = np.where(visible, 255.0 * opacities_eff, 1.0)
    extend = np.minimum(MAX_EXTEND, np.sqrt(2.0 * np.log(ratio)))
    var_x = np.where(visible, cov2d[:, 0, 0], 0.0)
    var_y = np.where(visible, cov2d[:, 1, 1], 0.0)
    radius_x = np.ceil(extend * np.sqrt(np.maximum(var_x, 0.0)))
    radius_y = np.ceil(extend * np.sqrt(np.maximum(var_y, 0.0)))
    visible &= ~((radius_x <= 0) & (radius_y <= 0))
    mx, my = means2d[:, 0], means2d[:, 1]
    off_screen = ((mx + radius_x <= 0) | (mx - radius_x >= width)
                  | (my + radius_y <= 0) | (my - radius_y >= height))
    visible &= ~off_screen
    radii = np.where(visible[:, None], np.stack([radius_x, radius_y], axis=-1), 0.0)
    radii = radii.astype(np.int64)

    # Zero out everything about non-compositable Gaussians.
    keep = compositable
    means2d = np.where(keep[:, None], means2d, 0.0)
    conics = np.where(keep[:, None], conics, 0.0)
    cov2d = np.where(keep[:, None, None], cov2d, 0.0)
    opacities_eff = np.where(keep, opacities_eff, 0.0)
    compensation = np.where(keep, compensation, 0.0)

    return {
        "means2d": means2d,
        "conics": conics,
        "cov2d": cov2d,
        "depths": z.copy(),
        "radii": radii,
        "visible": visible,
        "opacities_eff": opacities_eff,
        "compensation": compensation,
        "compositable": compositable,
    }


def rasterize_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, *,
                        near=0.01, far=1e10, background=None, antialiased=False, eps2d=0.3, lens=None):
    """Project and alpha-composite Gaussians front to back (slow oracle).

    Args:
        means: [G, 3] world-space centres.
        quats: [G, 4] wxyz quaternions (need not be normalised).
        scales: [G, 3] linear standard deviations.
        opacities: [G] opacities in [0, 1].
        colors: [G, C] per-Gaussian colours / features, any C >= 1.
        viewmat: [4, 4] world-to-camera matrix (OpenCV axes).
        K: [3, 3] pinhole intrinsics.
        width, height: image size in pixels.
        near, far: depth clipping planes.
        background: [C] background colour, or None for zeros.
        antialiased: gsplat "antialiased" mode (opacity * compensation).
        eps2d: low-pass term added to the 2D covariance diagonal.
        lens: None or (coeffs, bounds, fisheye), as project_reference.

    Returns:
        dict with
            image [H, W, C] float64 (composited colour + T * background),
            alpha [H, W] float64 (1 - final transmittance),
            depth [H, W] float64 (sum of z * alpha * T, not normalised),
            n_contrib [H, W] int64 (number of Gaussians composited per pixel),
            radii [G, 2] int64, visible [G] bool,
            significance [G] float64 (sum over pixels of opacity_eff * T),
            hits [G] int64 (number of pixels the Gaussian was composited into),
            means2d [G, 2], conics [G, 3], depths [G], opacities_eff [G] float64.
    """
    width = int(width)
    height = int(height)
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    G = means.shape[0]
    colors = np.asarray(colors, dtype=np.float64)
    if colors.ndim == 1:                      # [G] -> [G, 1]
        colors = colors[:, None]
    C = colors.shape[1]
    if background is None:
        background = np.zeros(C, dtype=np.float64)
    background = np.asarray(background, dtype=np.float64).reshape(C)

    proj = project_reference(means, quats, scales, opacities, viewmat, K, width, height,
                             near=near, far=far, antialiased=antialiased, eps2d=eps2d, lens=lens)
    means2d = proj["means2d"]
    conics = proj["conics"]
    depths = proj["depths"]
    opac = proj["opacities_eff"]

    # Depth order of the compositable Gaussians; stable sort => ties by index.
    idx = np.nonzero(proj["compositable"])[0]
    order = idx[np.argsort(depths[idx], kind="stable")]

    # Pixel centres.                                                     [H,W]
    py, px = np.meshgrid(np.arange(height, dtype=np.float64) + 0.5,
                         np.arange(width, dtype=np.float64) + 0.5, indexing="ij")

    T = np.ones((height, width), dtype=np.float64)
    image = np.zeros((height, width, C), dtype=np.float64)
    depth = np.zeros((height, width), dtype=np.float64)
    n_contrib = np.zeros((height, width), dtype=np.int64)
    done = np.zeros((height, width), dtype=bool)
    significance = np.zeros(G, dtype=np.float64)
    hits = np.zeros(G, dtype=np.int64)

    for g in order:
        a, b, c = conics[g]
        dx = means2d[g, 0] - px
        dy = means2d[g, 1] - py
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = np.minimum(ALPHA_MAX, opac[g] * np.exp(-np.maximum(sigma, 0.0)))
        # Per pixel: skip if sigma < 0 or alpha < 1/255 ("continue").
        candidate = ~done & (sigma >= 0.0) & (alpha >= ALPHA_THRESHOLD)
        next_T = T * (1.0 - alpha)
        # Per pixel "break": this Gaussian is not composited, pixel is finished.
        stop = candidate & (next_T <= TRANSMITTANCE_MIN)
        done |= stop
        use = candidate & ~stop
        w = np.where(use, alpha * T, 0.0)
        image += w[:, :, None] * colors[g][None, None, :]
        depth += w * depths[g]
        significance[g] += np.sum(np.where(use, opac[g] * T, 0.0))
        hits[g] += int(np.count_nonzero(use))
        n_contrib += use
        T = np.where(use, next_T, T)

    image = image + T[:, :, None] * background[None, None, :]
    return {
        "image": image,
        "alpha": 1.0 - T,
        "depth": depth,
        "n_contrib": n_contrib,
        "radii": proj["radii"],
        "visible": proj["visible"],
        "significance": significance,
        "hits": hits,
        "means2d": means2d,
        "conics": conics,
        "depths": depths,
        "opacities_eff": opac,
    }
