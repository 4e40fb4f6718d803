"""cusgs_jax.extract.descriptors: the weight-free dense descriptors (daisy, hog, gabor,
semantic) on synthetic images and demo-scene views."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.loader import load_scene
from cusgs_jax.extract import descriptors as desc

W, H, V = 40, 30, 4  # the size of the `demo` fixture (tests/conftest.py TINY_DEMO)


def test_lab_triples_the_dimension(demo):
    img = load_scene(demo, DataConfig(format="colmap", holdout_every=0)).images[0]
    for fn, d in [(desc.daisy_features, 104), (desc.hog_features, 36), (desc.gabor_features, 18)]:
        grey, lab = fn(img), fn(img, lab=True)
        assert grey.shape == (H, W, d) and lab.shape == (H, W, 3 * d)
        assert grey.dtype == lab.dtype == np.float32
        assert np.linalg.norm(lab, axis=-1).max() <= 1.0 + 1e-5
        np.testing.assert_array_equal(fn(img, lab=True), lab)  # deterministic


@pytest.mark.parametrize("fn", [desc.daisy_features, desc.hog_features, desc.gabor_features])
@pytest.mark.parametrize("lab", [False, True])
def test_flat_image_gives_zero_vectors(fn, lab):
    flat = np.full((20, 24, 3), 137, np.uint8)
    assert not fn(flat, lab=lab).any()  # zero = no target


def test_daisy_matches_skimage_in_the_interior():
    from skimage import data, transform
    from skimage.feature import daisy

    img = (transform.resize(data.astronaut(), (100, 100), anti_aliasing=True) * 255).astype(
        np.uint8)
    ours = desc.daisy_features(img)
    grey = desc._channels(img, False)[0]
    ref = daisy(grey, step=1, radius=7, rings=2, histograms=6, orientations=8,
                normalization="off")  # ref[i, j] is centred on pixel (i + 7, j + 7)
    ref = ref / np.maximum(np.linalg.norm(ref, axis=-1, keepdims=True), 0.02)
    sl = slice(36, 64)  # farther than radius + 4·sigma from any border: no padding effects
    np.testing.assert_allclose(ours[sl, sl], ref[sl.start - 7:sl.stop - 7, sl.start - 7:sl.stop - 7],
                               atol=1e-5)


def test_gabor_matches_skimage_filters_gabor():
    from skimage import data, transform
    from skimage.filters import gabor

    grey = transform.resize(data.camera(), (30, 40), anti_aliasing=True)
    freqs = (0.1, 0.3)
    bank = desc._gabor_bank(freqs, 3, 1.0, zero_mean=False)
    ours = desc._gabor_channel(grey, bank)
    n = 0
    for f in freqs:
        for k in range(3):
            re, im = gabor(grey, f, theta=np.pi * k / 3, bandwidth=1.0, mode="reflect")
            np.testing.assert_allclose(ours[..., n], np.hypot(re, im), atol=1e-10)
            n += 1


def test_hog_blocks_are_centred_on_pixels():
    # A vertical step edge between columns 19 and 20: mirror image (flip + invert) of itself
    # about x = 20.0, so the block at pixel 19 (centre 19.5) mirrors the one at pixel 20
    # (centre 20.5): its left cells equal the other's right cells.
    img = np.zeros((30, 40, 3), np.uint8)
    img[:, 20:] = 255
    f = desc.hog_features(img, cell=4, orientations=9).reshape(30, 40, 2, 2, 9)  # rows, cols
    np.testing.assert_allclose(f[:, 19, :, 0], f[:, 20, :, 1], atol=1e-6)
    np.testing.assert_allclose(f[:, 19, :, 1], f[:, 20, :, 0], atol=1e-6)
    assert np.abs(f[:, 19, :, 0] - f[:, 19, :, 1]).max() > 0.05  # not trivially symmetric
    assert not f[:, :10].any() and not f[:, 30:].any()  # far from the edge: flat, no target


def test_semantic_palette_is_orthonormal_up_to_dim_ids():
    table = desc.semantic_palette(dim=32, seed=0, num_ids=40)
    first = table[1:33].astype(np.float64)
    np.testing.assert_allclose(first @ first.T, np.eye(32), atol=1e-6)
    assert np.all(table[0] == 0)
    np.testing.assert_allclose(np.linalg.norm(table[33:], axis=1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(desc.semantic_palette(dim=32, seed=0, num_ids=10), table[:10])


def test_daisy_is_view_consistent(tmp_path):
    """A surface point's descriptors in two neighbouring views (15° apart) are more similar than
    random pairs of pixels (correspondences from the demo scene's exact depth and poses)."""
    views, w, h = 24, 80, 60
    scene_dir = generate_demo_scene(tmp_path / "orbit", num_views=views, width=w, height=h,
                                    num_points=300)
    scene = load_scene(scene_dir, DataConfig(format="colmap", holdout_every=0))
    rng = np.random.default_rng(0)
    for a in (0, 7, 15):
        b = a + 1
        depth_a = np.load(scene_dir / "depth" / f"view_{a:03d}.npy").astype(np.float64)
        depth_b = np.load(scene_dir / "depth" / f"view_{b:03d}.npy").astype(np.float64)
        i, j = np.nonzero(depth_a > 0)
        z = depth_a[i, j]
        K = scene.Ks[a].astype(np.float64)
        cam = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0] * z, (i + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
        va, vb = scene.viewmats[a].astype(np.float64), scene.viewmats[b].astype(np.float64)
        world = (cam - va[:3, 3]) @ va[:3, :3]
        xb = world @ vb[:3, :3].T + vb[:3, 3]
        Kb = scene.Ks[b].astype(np.float64)
        jb = np.floor(Kb[0, 0] * xb[:, 0] / xb[:, 2] + Kb[0, 2]).astype(int)
        ib = np.floor(Kb[1, 1] * xb[:, 1] / xb[:, 2] + Kb[1, 2]).astype(int)
        ok = (xb[:, 2] > 0) & (jb >= 0) & (jb < w) & (ib >= 0) & (ib < h)
        ok[ok] &= np.abs(depth_b[ib[ok], jb[ok]] - xb[ok, 2]) < 0.01 * xb[ok, 2]  # visible in b
        assert ok.sum() > 500
        fa = desc.daisy_features(scene.images[a])[i[ok], j[ok]]
        fb = desc.daisy_features(scene.images[b])[ib[ok], jb[ok]]
        match = np.sum(fa * fb, -1)
        rand = np.sum(fa * fb[rng.permutation(len(fb))], -1)
        assert np.median(match) > np.median(rand) + 0.05
        assert np.mean(match > rand) > 0.8  # measured ≈ 0.93–0.97
