"""Closed-form checks of the float64 NumPy reference rasteriser (the test oracle)."""

import math

import numpy as np
import pytest

from cusgs_jax.testing.splat_reference import project_reference, rasterize_reference

W, H = 16, 12
F = 100.0


def _K(cx=W / 2, cy=H / 2, f=F):
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _scene(zs, scale, opacities, colors, xy=None):
    """Isotropic Gaussians at (0, 0, z) (or given xy) with identity rotation."""
    g = len(zs)
    means = np.zeros((g, 3))
    means[:, 2] = zs
    if xy is not None:
        means[:, :2] = xy
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (g, 1))
    scales = np.full((g, 3), scale, dtype=np.float64)
    return (means, quats, scales, np.asarray(opacities, float),
            np.asarray(colors, float).reshape(g, -1))


def _pixel_grid():
    py, px = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    return px, py


def _on_axis_alpha(z, s, opacity, cx, cy, eps2d=0.3):
    """Closed-form alpha map of one isotropic Gaussian on the optical axis."""
    v = (F * s / z) ** 2 + eps2d            # Sigma2d = v * I
    px, py = _pixel_grid()
    sigma = 0.5 * ((cx - px) ** 2 + (cy - py) ** 2) / v
    alpha = np.minimum(0.999, opacity * np.exp(-sigma))
    return np.where(alpha < 1 / 255, 0.0, alpha)


def test_single_gaussian_closed_form():
    z, s, o = 5.0, 0.1, 0.5
    col = np.array([1.0, 0.5, 0.25])
    out = rasterize_reference(*_scene([z], s, [o], [col]), np.eye(4), _K(), W, H)
    alpha = _on_axis_alpha(z, s, o, W / 2, H / 2)
    assert alpha.max() > 0.4 and (alpha == 0).any()       # test is meaningful
    np.testing.assert_allclose(out["image"], alpha[:, :, None] * col, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["alpha"], alpha, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["depth"], z * alpha, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(out["n_contrib"], (alpha > 0).astype(int))
    assert out["hits"][0] == np.count_nonzero(alpha)
    np.testing.assert_allclose(out["significance"][0], o * np.count_nonzero(alpha))

    # Projection quantities.
    v = (F * s / z) ** 2 + 0.3
    np.testing.assert_allclose(out["means2d"], [[W / 2, H / 2]])
    np.testing.assert_allclose(out["conics"], [[1 / v, 0.0, 1 / v]], atol=1e-15)
    np.testing.assert_allclose(out["depths"], [z])
    r = math.ceil(min(3.33, math.sqrt(2 * math.log(255 * o))) * math.sqrt(v))
    np.testing.assert_array_equal(out["radii"], [[r, r]])
    assert out["visible"].tolist() == [True]


def test_two_gaussians_front_to_back_and_index_swap():
    (z1, o1, c1), (z2, o2, c2) = (3.0, 0.6, [1.0, 0.0, 0.2]), (6.0, 0.7, [0.0, 1.0, 0.5])
    s = 0.08
    cx, cy = 8.5, 6.5                              # means on pixel (6, 8) centre
    a1 = _on_axis_alpha(z1, s, o1, cx, cy)
    a2 = _on_axis_alpha(z2, s, o2, cx, cy)
    expected = (np.asarray(c1) * a1[:, :, None]
                + np.asarray(c2) * (a2 * (1 - a1))[:, :, None])
    K = _K(cx, cy)
    out_a = rasterize_reference(*_scene([z1, z2], s, [o1, o2], [c1, c2]), np.eye(4), K, W, H)
    out_b = rasterize_reference(*_scene([z2, z1], s, [o2, o1], [c2, c1]), np.eye(4), K, W, H)
    np.testing.assert_allclose(out_a["image"], expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out_b["image"], expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out_a["alpha"], 1 - (1 - a1) * (1 - a2), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out_a["depth"], z1 * a1 + z2 * a2 * (1 - a1), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out_b["significance"], out_a["significance"][::-1])
    # Back-to-front would give a different colour at the centre.
    wrong = np.asarray(c2) * a2[6, 8] + np.asarray(c1) * a1[6, 8] * (1 - a2[6, 8])
    assert not np.allclose(out_a["image"][6, 8], wrong)


def test_equal_depth_ties_broken_by_index():
    s, o = 0.1, 0.5
    out = rasterize_reference(*_scene([4.0, 4.0], s, [o, o], [[1.0], [0.0]]),
                              np.eye(4), _K(8.5, 6.5), W, H)
    a = _on_axis_alpha(4.0, s, o, 8.5, 6.5)
    np.testing.assert_allclose(out["image"][..., 0], a, rtol=1e-12)  # index 0 is in front


def test_alpha_clamped_at_0999():
    out = rasterize_reference(*_scene([5.0], 0.1, [1.0], [[1.0, 1.0, 1.0]]),
                              np.eye(4), _K(8.5, 6.5), W, H)
    assert out["alpha"][6, 8] == pytest.approx(0.999, abs=1e-15)
    np.testing.assert_allclose(out["image"][6, 8], 0.999, atol=1e-15)
    assert out["alpha"].max() == pytest.approx(0.999, abs=1e-15)


def test_early_termination():
    n = 6
    zs = 2.0 + np.arange(n)
    cols = np.eye(n)                       # one-hot colour per Gaussian
    out = rasterize_reference(*_scene(zs, 0.05, [0.9] * n, cols),
                              np.eye(4), _K(8.5, 6.5), W, H)
    # Hand computation at the centre pixel: alpha = 0.9 for each Gaussian.
    T, weights = 1.0, []
    for _ in range(n):
        if T * (1 - 0.9) <= 1e-4:
            break
        weights.append(0.9 * T)
        T *= 1 - 0.9
    assert len(weights) == 3               # 0.1**4 = 1e-4 <= 1e-4 stops the 4th
    assert out["n_contrib"][6, 8] == 3
    np.testing.assert_allclose(out["image"][6, 8], weights + [0.0] * (n - 3), rtol=1e-12)
    assert out["alpha"][6, 8] == pytest.approx(1 - T, rel=1e-12)
    # Gaussians behind the termination point get nothing at the centre pixel,
    # and a terminated pixel stays terminated.
    assert out["image"][6, 8, 3:].sum() == 0.0


def test_behind_camera_and_near_plane_culled():
    col = [[1.0, 1.0, 1.0]] * 3
    means, quats, scales, opac, cols = _scene([-5.0, 0.005, 5.0], 0.1, [0.8] * 3, col)
    out = rasterize_reference(means, quats, scales, opac, cols, np.eye(4), _K(), W, H)
    only = rasterize_reference(*_scene([5.0], 0.1, [0.8], col[:1]), np.eye(4), _K(), W, H)
    np.testing.assert_array_equal(out["image"], only["image"])
    assert out["visible"].tolist() == [False, False, True]
    np.testing.assert_array_equal(out["radii"][:2], 0)
    np.testing.assert_array_equal(out["hits"][:2], 0)
    np.testing.assert_array_equal(out["significance"][:2], 0.0)
    # Beyond far is culled as well.
    far = rasterize_reference(means, quats, scales, opac, cols, np.eye(4), _K(), W, H, far=4.0)
    assert far["alpha"].max() == 0.0 and not far["visible"].any()


def test_jacobian_clamp_off_axis():
    z, s = 4.0, 0.1
    xy = np.array([[10.0 * z, -0.05 * z], [0.0, -12.0 * z]])   # far right / far above
    scene = _scene([z, z], s, [0.5, 0.5], [[1.0], [1.0]], xy=xy)
    cx, cy = 7.0, 5.0
    proj = project_reference(*scene[:4], np.eye(4), _K(cx, cy), W, H)
    lim_x_pos = (W - cx) / F + 0.3 * 0.5 * W / F
    lim_y_neg = cy / F + 0.3 * 0.5 * H / F
    for g, (tx, ty) in enumerate([(z * lim_x_pos, xy[0, 1]), (xy[1, 0], -z * lim_y_neg)]):
        j0 = np.array([F / z, 0.0, -F * tx / z ** 2])
        j1 = np.array([0.0, F / z, -F * ty / z ** 2])
        cov = s * s * np.array([[j0 @ j0, j0 @ j1], [j1 @ j0, j1 @ j1]]) + 0.3 * np.eye(2)
        np.testing.assert_allclose(proj["cov2d"][g], cov, rtol=1e-12, atol=1e-15)
        # The mean itself is not clamped.
        np.testing.assert_allclose(proj["means2d"][g], F * xy[g] / z + [cx, cy], rtol=1e-12)
    # Far off screen: still compositable, but not visible and radii 0.
    assert proj["compositable"].all() and not proj["visible"].any()
    np.testing.assert_array_equal(proj["radii"], 0)


def test_antialiased_compensation():
    z, s, o = 5.0, 0.03, 0.8
    scene = _scene([z], s, [o], [[1.0]])
    u = (F * s / z) ** 2
    v = u + 0.3
    comp = u / v                                   # sqrt(det_orig / det) = sqrt(u^2 / v^2)
    out = rasterize_reference(*scene, np.eye(4), _K(8.5, 6.5), W, H, antialiased=True)
    plain = rasterize_reference(*scene, np.eye(4), _K(8.5, 6.5), W, H)
    np.testing.assert_allclose(out["opacities_eff"], [o * comp], rtol=1e-12)
    np.testing.assert_allclose(plain["opacities_eff"], [o])
    np.testing.assert_allclose(out["image"][..., 0], _on_axis_alpha(z, s, o * comp, 8.5, 6.5),
                               rtol=1e-12)


def test_background_only():
    bg = np.array([0.2, 0.4, 0.6])
    out = rasterize_reference(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)),
                              np.zeros(0), np.zeros((0, 3)), np.eye(4), _K(), W, H,
                              background=bg)
    assert out["image"].shape == (H, W, 3)
    np.testing.assert_array_equal(out["image"], np.broadcast_to(bg, (H, W, 3)))
    np.testing.assert_array_equal(out["alpha"], 0.0)
    np.testing.assert_array_equal(out["n_contrib"], 0)
    # Background is blended with the remaining transmittance.
    one = rasterize_reference(*_scene([5.0], 0.1, [0.5], [[0.0, 0.0, 0.0]]),
                              np.eye(4), _K(), W, H, background=bg)
    np.testing.assert_allclose(one["image"], (1 - one["alpha"])[:, :, None] * bg, rtol=1e-12)


def test_quaternion_robustness():
    means, _, _, opac, cols = _scene([5.0] * 4, 0.1, [0.6] * 4, [[1.0, 0.5, 0.2]] * 4)
    scales = np.array([[0.05, 0.1, 0.2]] * 4)
    q = np.array([0.3, -0.5, 0.7, 0.2])
    quats = np.stack([np.zeros(4), q * 1e-20 / np.linalg.norm(q),
                      q * 1e20 / np.linalg.norm(q), q * 1e-300])
    for i in range(4):
        out = rasterize_reference(means[i:i + 1], quats[i:i + 1], scales[:1], opac[:1],
                                  cols[:1], np.eye(4), _K(), W, H)
        for key in ("image", "alpha", "depth", "conics", "means2d"):
            assert np.all(np.isfinite(out[key])), (i, key)
        assert out["alpha"].max() > 0.1
    # Zero quaternion == identity.
    ident = rasterize_reference(means[:1], [[1.0, 0, 0, 0]], scales[:1], opac[:1], cols[:1],
                                np.eye(4), _K(), W, H)
    zero = rasterize_reference(means[:1], [[0.0, 0, 0, 0]], scales[:1], opac[:1], cols[:1],
                               np.eye(4), _K(), W, H)
    np.testing.assert_allclose(zero["image"], ident["image"], rtol=1e-14)
    # A quaternion and its scalar multiples (including negative) agree.
    base = rasterize_reference(means[:1], [q], scales[:1], opac[:1], cols[:1],
                               np.eye(4), _K(), W, H)
    assert not np.allclose(base["image"], ident["image"])   # rotation matters here
    for k in (1e-20, 1e20, -3.0, 7.5):
        other = rasterize_reference(means[:1], [q * k], scales[:1], opac[:1], cols[:1],
                                    np.eye(4), _K(), W, H)
        np.testing.assert_allclose(other["image"], base["image"], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(other["conics"], base["conics"], rtol=1e-12)


def _composite_scalar(proj, colors, W, H):
    """Literal per-pixel loop from the spec, for cross-checking the vectorised one."""
    idx = np.nonzero(proj["compositable"])[0]
    order = idx[np.argsort(proj["depths"][idx], kind="stable")]
    img = np.zeros((H, W, colors.shape[1]))
    n_contrib = np.zeros((H, W), int)
    sig = np.zeros(len(colors))
    hits = np.zeros(len(colors), int)
    n_broken = 0
    for i in range(H):
        for j in range(W):
            px, py = j + 0.5, i + 0.5
            T, Cc, n = 1.0, np.zeros(colors.shape[1]), 0
            for g in order:
                a, b, c = proj["conics"][g]
                dx = proj["means2d"][g, 0] - px
                dy = proj["means2d"][g, 1] - py
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:
                    continue
                alpha = min(0.999, proj["opacities_eff"][g] * math.exp(-sigma))
                if alpha < 1 / 255:
                    continue
                next_T = T * (1 - alpha)
                if next_T <= 1e-4:
                    n_broken += 1
                    break
                Cc += colors[g] * alpha * T
                sig[g] += proj["opacities_eff"][g] * T
                hits[g] += 1
                n += 1
                T = next_T
            img[i, j] = Cc
            n_contrib[i, j] = n
    return img, n_contrib, sig, hits, n_broken


def test_random_scene_matches_scalar_loop_and_projection_invariants():
    rng = np.random.default_rng(0)
    G = 80
    means = np.column_stack([rng.uniform(-1.5, 1.5, G), rng.uniform(-1.2, 1.2, G),
                             rng.uniform(0.0, 5.0, G)])
    means[:5, 2] = -2.0                         # a few behind the camera
    quats = rng.normal(size=(G, 4))
    scales = rng.uniform(0.05, 0.6, (G, 3))
    opac = rng.uniform(0.0, 1.0, G) ** 0.3
    cols = rng.uniform(0.0, 1.0, (G, 2))
    # A rotated, translated camera.
    ang = 0.3
    Rv = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0],
                   [-math.sin(ang), 0, math.cos(ang)]])
    view = np.eye(4)
    view[:3, :3] = Rv
    view[:3, 3] = [0.1, -0.2, 0.5]
    K = np.array([[20.0, 0, 7.3], [0, 22.0, 6.1], [0, 0, 1]])
    out = rasterize_reference(means, quats, scales, opac, cols, view, K, W, H)
    proj = project_reference(means, quats, scales, opac, view, K, W, H)
    img, n_contrib, sig, hits, n_broken = _composite_scalar(proj, cols, W, H)
    assert 0 < n_broken < W * H                 # early termination is exercised
    np.testing.assert_allclose(out["image"], img, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(out["n_contrib"], n_contrib)
    np.testing.assert_allclose(out["significance"], sig, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(out["hits"], hits)
    assert out["n_contrib"].sum() == out["hits"].sum()
    assert (out["n_contrib"] > 0).any() and proj["compositable"].sum() < G
    # Conics are the inverse of the low-passed 2D covariance.
    for g in np.nonzero(proj["compositable"])[0]:
        a, b, c = proj["conics"][g]
        np.testing.assert_allclose(np.array([[a, b], [b, c]]) @ proj["cov2d"][g], np.eye(2),
                                   atol=1e-9)
    # Visible implies compositable; invisible has zero radii.
    assert not (proj["visible"] & ~proj["compositable"]).any()
    np.testing.assert_array_equal(proj["radii"][~proj["visible"]], 0)
