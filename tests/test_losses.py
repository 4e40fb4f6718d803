"""Losses: SSIM against skimage, gradients, numerical safety, L1 / volume / combined loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage import data as skdata
from skimage.filters import gaussian as sk_gaussian
from skimage.metrics import structural_similarity
from skimage.transform import resize

from cusgs_jax.losses import (
    gaussian_window,
    image_loss,
    l1,
    ssim,
    ssim_loss,
    ssim_map,
    volume_regularizer,
)

TOL = 1e-4


def sk_ssim(a, b, full=False):
    return structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64), gaussian_weights=True,
                                 sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1,
                                 full=full)


def _pair(shape, seed=0, noise=0.15):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, shape)
    b = np.clip(a + noise * rng.normal(size=shape), 0, 1)
    return a.astype(np.float32), b.astype(np.float32)


@pytest.fixture(scope="module")
def astronaut():
    img = resize(skdata.astronaut() / 255.0, (64, 64, 3), anti_aliasing=True)
    rng = np.random.default_rng(3)
    degraded = np.clip(sk_gaussian(img, sigma=1.0, channel_axis=-1) + 0.05 * rng.normal(size=img.shape), 0, 1)
    return img.astype(np.float32), degraded.astype(np.float32)


def test_window_is_scipys_11_tap_gaussian():
    from scipy.ndimage import gaussian_filter1d

    w = gaussian_window()
    assert w.shape == (11,)
    impulse = np.zeros(31)
    impulse[15] = 1.0
    np.testing.assert_allclose(w, gaussian_filter1d(impulse, 1.5, truncate=3.5)[10:21], atol=1e-15)


@pytest.mark.parametrize("shape", [(32, 32, 3), (37, 29, 3), (29, 37, 1), (11, 11, 3), (12, 40, 2)])
def test_ssim_matches_skimage_random(shape):
    a, b = _pair(shape, seed=sum(shape))
    assert abs(float(ssim(a, b)) - sk_ssim(a, b)) < TOL
    # Unrelated images too (SSIM near 0).
    c = np.random.default_rng(1).uniform(0, 1, shape).astype(np.float32)
    assert abs(float(ssim(a, c)) - sk_ssim(a, c)) < TOL


def test_ssim_matches_skimage_natural(astronaut):
    img, degraded = astronaut
    val = float(ssim(img, degraded))
    ref = sk_ssim(img, degraded)
    assert 0.2 < ref < 0.95  # a meaningful, non-trivial pair
    assert abs(val - ref) < TOL
    # Single channel (luminance), given as [H, W, 1] and as [H, W].
    g1, g2 = img.mean(-1, keepdims=True), degraded.mean(-1, keepdims=True)
    ref_gray = sk_ssim(g1, g2)
    assert abs(float(ssim(g1, g2)) - ref_gray) < TOL
    assert abs(float(ssim(g1[..., 0], g2[..., 0])) - ref_gray) < TOL
    # Brightness / contrast change of a natural image.
    assert abs(float(ssim(img, 0.7 * img + 0.2)) - sk_ssim(img, 0.7 * img + 0.2)) < TOL


def test_ssim_map_is_skimage_full_map_cropped(astronaut):
    img, degraded = astronaut
    _, full = sk_ssim(img, degraded, full=True)
    m = np.asarray(ssim_map(img, degraded))
    assert m.shape == (54, 54, 3)
    np.testing.assert_allclose(m, full[5:-5, 5:-5], atol=TOL)


def test_ssim_float64_matches_skimage_to_rounding(x64):
    a, b = _pair((37, 29, 3), seed=5)
    a, b = a.astype(np.float64), b.astype(np.float64)
    out = ssim(a, b)
    assert out.dtype == jnp.float64
    assert abs(float(out) - sk_ssim(a, b)) < 1e-12


def test_ssim_identical_is_one(astronaut):
    img, _ = astronaut
    for x in (img, np.zeros((16, 16, 3), np.float32), np.full((16, 16, 3), 0.4, np.float32)):
        assert abs(float(ssim(x, x)) - 1.0) < 1e-6
        assert abs(float(ssim_loss(x, x))) < 1e-6


def test_ssim_gradient_matches_finite_differences(x64):
    a, b = _pair((17, 15, 2), seed=11, noise=0.2)
    a, b = jnp.asarray(a, jnp.float64), jnp.asarray(b, jnp.float64)
    f = jax.jit(ssim)
    grad = np.asarray(jax.jit(jax.grad(ssim))(a, b))
    rng = np.random.default_rng(0)
    eps = 1e-6
    for _ in range(6):
        idx = tuple(int(rng.integers(0, n)) for n in a.shape)
        fd = (float(f(a.at[idx].add(eps), b)) - float(f(a.at[idx].add(-eps), b))) / (2 * eps)
        assert abs(grad[idx] - fd) < 1e-7 + 1e-5 * abs(fd), (idx, grad[idx], fd)
    # Border pixels (outside every kept window centre but inside windows) get gradient too.
    assert np.abs(grad[0]).max() > 0


@jax.jit
def _loss_and_grads(pred, target, scales):
    val, grads = jax.value_and_grad(lambda p, s: image_loss(p, target, s)[0], argnums=(0, 1))(pred, scales)
    return val, grads, jax.grad(ssim)(pred, target)


@pytest.mark.parametrize("case", ["constant", "zeros", "identical", "const_vs_noise"])
def test_gradients_finite(case):
    rng = np.random.default_rng(2)
    noise = jnp.asarray(rng.uniform(0, 1, (16, 16, 3)), jnp.float32)
    const = jnp.full((16, 16, 3), 0.5, jnp.float32)
    zeros = jnp.zeros((16, 16, 3), jnp.float32)
    pred, target = {"constant": (const, const * 0.9), "zeros": (zeros, zeros), "identical": (noise, noise),
                    "const_vs_noise": (const, noise)}[case]
    val, (gp, gs), g_ssim = _loss_and_grads(pred, target, jnp.zeros((5, 3), jnp.float32))
    assert np.isfinite(float(val))
    for g in (gp, gs, g_ssim):
        assert np.all(np.isfinite(np.asarray(g)))
    if case == "identical":  # SSIM is maximal: value 1, gradient ~0.
        assert abs(float(val)) < 1e-6
        assert np.abs(np.asarray(g_ssim)).max() < 1e-4


def test_ssim_rejects_small_or_mismatched():
    with pytest.raises(ValueError):
        ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))
    with pytest.raises(ValueError):
        ssim(np.zeros((20, 20, 3)), np.zeros((20, 20, 1)))


def test_l1_plain_and_masked():
    rng = np.random.default_rng(4)
    a = rng.uniform(size=(8, 6, 3)).astype(np.float32)
    b = rng.uniform(size=(8, 6, 3)).astype(np.float32)
    assert abs(float(l1(a, b)) - np.abs(a - b).mean()) < 1e-6
    mask = rng.uniform(size=(8, 6)) > 0.5
    ref = np.abs(a - b)[mask].mean()
    assert abs(float(l1(a, b, mask)) - ref) < 1e-6
    w = rng.uniform(size=(8, 6)).astype(np.float32)
    ref_w = (w[..., None] * np.abs(a - b)).sum() / (w.sum() * 3)
    assert abs(float(l1(a, b, w)) - ref_w) < 1e-6
    assert float(l1(a, b, np.zeros((8, 6), bool))) == 0.0
    g = jax.jit(jax.grad(l1))(jnp.asarray(a), jnp.asarray(b), jnp.zeros((8, 6)))
    assert np.all(np.isfinite(np.asarray(g)))


def test_volume_regularizer():
    rng = np.random.default_rng(6)
    s = rng.uniform(0.01, 0.5, (20, 3)).astype(np.float32)
    assert abs(float(volume_regularizer(s)) - s.prod(-1).mean()) < 1e-7
    mask = np.arange(20) % 3 == 0
    assert abs(float(volume_regularizer(s, mask)) - s[mask].prod(-1).mean()) < 1e-7
    assert float(volume_regularizer(s, np.zeros(20, bool))) == 0.0
    # Garbage in unselected rows affects neither value nor gradient.
    bad = s.copy()
    bad[~mask] = np.inf
    bad[1, 0] = np.nan
    val, grad = jax.jit(jax.value_and_grad(volume_regularizer))(jnp.asarray(bad), jnp.asarray(mask))
    assert abs(float(val) - s[mask].prod(-1).mean()) < 1e-7
    grad = np.asarray(grad)
    assert np.all(np.isfinite(grad)) and np.all(grad[~mask] == 0)
    ref = np.zeros_like(s)
    for j in range(3):
        ref[mask, j] = np.prod(np.delete(s[mask], j, axis=1), axis=1) / mask.sum()
    np.testing.assert_allclose(grad, ref, rtol=1e-5)


def test_image_loss_combines_terms(astronaut):
    img, degraded = astronaut
    rng = np.random.default_rng(8)
    scales = rng.uniform(0.05, 0.5, (30, 3)).astype(np.float32)
    mask = rng.uniform(size=30) > 0.4
    loss, terms = image_loss(img, degraded, scales, mask)
    assert set(terms) == {"l1", "ssim", "ssim_loss", "volume", "loss"}
    assert abs(float(terms["l1"]) - np.abs(img - degraded).mean()) < 1e-6
    assert abs(float(terms["ssim"]) - sk_ssim(img, degraded)) < TOL
    assert abs(float(terms["volume"]) - scales[mask].prod(-1).mean()) < 1e-7
    expected = 0.8 * terms["l1"] + 0.2 * (1 - terms["ssim"]) + 0.01 * terms["volume"]
    assert abs(float(loss) - float(expected)) < 1e-6
    assert float(terms["loss"]) == float(loss)
    # Custom weights, no scales, a pixel mask.
    pm = np.zeros((64, 64), bool)
    pm[:32] = True
    loss2, terms2 = image_loss(img, degraded, pixel_mask=pm, l1_weight=1.0, ssim_weight=0.5, volume_weight=3.0)
    assert float(terms2["volume"]) == 0.0
    assert abs(float(terms2["l1"]) - np.abs(img - degraded)[:32].mean()) < 1e-6
    assert abs(float(loss2) - float(terms2["l1"] + 0.5 * terms2["ssim_loss"])) < 1e-6


def test_everything_jits(astronaut):
    img, degraded = astronaut
    scales = jnp.full((4, 3), 0.1)
    mask = jnp.array([True, False, True, True])
    # Jitted and eager float32 results differ only by rounding (XLA fuses differently).
    for fn, args, atol in [(ssim, (img, degraded), 1e-6), (ssim_loss, (img, degraded), 1e-6),
                           (ssim_map, (img, degraded), 1e-4), (l1, (img, degraded), 1e-7),
                           (l1, (img, degraded, jnp.ones((64, 64))), 1e-7),
                           (volume_regularizer, (scales,), 1e-8), (volume_regularizer, (scales, mask), 1e-8)]:
        np.testing.assert_allclose(np.asarray(jax.jit(fn)(*args)), np.asarray(fn(*args)), rtol=1e-6, atol=atol)
    loss_fn = jax.jit(lambda p, t, s, m: image_loss(p, t, s, m))
    loss, terms = loss_fn(img, degraded, scales, mask)
    ref_loss, _ = image_loss(img, degraded, scales, mask)
    assert abs(float(loss) - float(ref_loss)) < 1e-6
    g = jax.jit(jax.grad(lambda p: image_loss(p, degraded, scales, mask)[0]))(jnp.asarray(img))
    assert g.shape == img.shape and np.all(np.isfinite(np.asarray(g)))


def test_masked_ssim_and_loss_ignore_invalid_pixels(astronaut):
    """A valid-pixel mask: SSIM is skimage's map of both images zeroed outside the mask, averaged over
    the valid pixels of the border-cropped grid; L1 is the mean over the valid pixels; the invalid
    pixels get no gradient, and changing them (in pred or in target) changes nothing."""
    img, degraded = (np.asarray(x, np.float64) for x in astronaut)
    rng = np.random.default_rng(3)
    valid = np.ones(img.shape[:2], bool)
    valid[:10] = False
    valid[:, -7:] = False
    valid[rng.uniform(size=valid.shape) < 0.05] = False
    zeroed = lambda x: np.where(valid[..., None], x, 0.0)  # noqa: E731
    _, full = sk_ssim(zeroed(degraded), zeroed(img), full=True)
    r = 5
    expected = full[r:-r, r:-r][valid[r:-r, r:-r]].mean()
    got = float(ssim(degraded.astype(np.float32), img.astype(np.float32), mask=valid))
    assert abs(got - expected) < TOL
    assert abs(got - float(ssim(degraded.astype(np.float32), img.astype(np.float32)))) > 1e-3  # the mask matters
    loss, terms = image_loss(degraded.astype(np.float32), img.astype(np.float32), pixel_mask=valid)
    assert abs(float(terms["l1"]) - np.abs(degraded - img)[valid].mean()) < 1e-6
    # pred's invalid pixels: no gradient, and any value there gives the same loss
    grad = jax.grad(lambda p: image_loss(p, jnp.asarray(img, jnp.float32), pixel_mask=valid)[0])(
        jnp.asarray(degraded, jnp.float32))
    assert np.all(np.asarray(grad)[~valid] == 0) and np.any(np.asarray(grad)[valid] != 0)
    scrambled = np.where(valid[..., None], degraded, rng.uniform(size=img.shape)).astype(np.float32)
    assert float(image_loss(scrambled, img.astype(np.float32), pixel_mask=valid)[0]) == float(loss)
    other = np.where(valid[..., None], img, rng.uniform(size=img.shape)).astype(np.float32)
    assert float(image_loss(degraded.astype(np.float32), other, pixel_mask=valid)[0]) == float(loss)
    # an all-valid mask is the unmasked loss
    np.testing.assert_allclose(float(image_loss(degraded, img, pixel_mask=np.ones_like(valid))[0]),
                               float(image_loss(degraded, img)[0]), rtol=1e-6)
