"""Viewer modes: depth/alpha/PCA pictures and the Otsu-thresholded query heatmap (NumPy only)."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.eval.feature_metrics import retrieval_scores, similarity_mask
from cusgs_jax.view.modes import (Frame, alpha_grey, colourise, depth_colours, feature_of_mode, mode_names,
                                  pca_colours, pixel_at, query_heatmap)


def _frame(h=6, w=8, d=5, seed=0):
    rng = np.random.default_rng(seed)
    alpha = np.ones((h, w), np.float32)
    alpha[0] = 0.0  # an uncovered row
    feats = rng.normal(size=(h, w, d)).astype(np.float32)
    feats[:, : w // 2] += 4 * np.eye(d, dtype=np.float32)[0]  # two "objects": left and right halves
    feats[:, w // 2:] += 4 * np.eye(d, dtype=np.float32)[1]
    depth = np.tile(np.linspace(1, 3, w, dtype=np.float32), (h, 1)) * alpha
    return Frame(rgb=rng.uniform(size=(h, w, 3)).astype(np.float32), depth=depth, alpha=alpha, features={"sem": feats})


def test_mode_names_and_their_feature_models():
    assert mode_names(["a", "b"]) == ["RGB", "depth", "alpha", "PCA a", "PCA b", "query a", "query b"]
    assert [feature_of_mode(m) for m in ("RGB", "PCA a", "query b")] == [None, "a", "b"]


def test_depth_is_turbo_near_red_far_blue_and_black_where_uncovered():
    f = _frame()
    pic = depth_colours(f.depth, f.alpha)
    assert pic.dtype == np.uint8 and pic.shape == (6, 8, 3)
    assert (pic[0] == 0).all()
    near, far = pic[3, 0].astype(int), pic[3, -1].astype(int)
    assert near[0] > near[2] and far[2] > far[0]
    assert (depth_colours(f.depth, np.zeros_like(f.alpha)) == 0).all()


def test_alpha_grey_and_pca_colours():
    f = _frame()
    assert (alpha_grey(f.alpha)[0] == 0).all() and (alpha_grey(f.alpha)[1] == 255).all()
    pca = pca_colours(f.features["sem"], f.alpha)
    left, right = pca[1:, :4].reshape(-1, 3).mean(0), pca[1:, 4:].reshape(-1, 3).mean(0)
    assert np.abs(left - right).max() > 50  # the two objects get different colours
    assert (pca_colours(np.zeros((4, 4, 3)), None) == 0).all()


def test_the_query_heatmap_uses_the_retrieval_metrics_otsu_threshold():
    f = _frame()
    query = f.features["sem"][3, 1]  # a pixel of the left object
    pic, thr, share = query_heatmap(f.features["sem"], query, f.rgb, f.alpha)
    scores, thr2, mask = similarity_mask(f.features["sem"], query, f.alpha >= 1e-3)
    assert thr == thr2 and mask[1:, :4].all() and not mask[:, 4:].any() and share == pytest.approx(0.5)
    ids = np.zeros((1, 6, 8), int)
    ids[0, 1:, :4] = 1
    metric = retrieval_scores(f.features["sem"][None], ids, {1: query}, valid=(f.alpha >= 1e-3)[None])
    assert metric["thresholds"][1] == pytest.approx(thr) and metric["per_object"][1] == 1.0
    outside = np.round(0.33 * f.rgb[2, 6] * 255)
    np.testing.assert_allclose(pic[2, 6], outside, atol=1)  # outside the mask: the RGB darkened
    _, none, _ = query_heatmap(np.ones((3, 3, 2)), np.array([1.0, 0.0]), np.zeros((3, 3, 3)))
    assert none is None  # constant scores: nothing to threshold


def test_colourise_every_mode_and_the_query_hint():
    f = _frame()
    for mode in mode_names(["sem"]):
        pic, note = colourise(mode, f, None)
        assert pic.shape == (6, 8, 3) and pic.dtype == np.uint8
    assert "click a pixel" in colourise("query sem", f)[1]
    assert "Otsu threshold" in colourise("query sem", f, f.features["sem"][2, 2])[1]
    with pytest.raises(ValueError, match="unknown mode"):
        colourise("PCA nope", f)


def test_pixel_at_clamps_to_the_image():
    assert pixel_at((0.0, 0.0), 8, 6) == (0, 0)
    assert pixel_at((1.0, 1.0), 8, 6) == (5, 7)
    assert pixel_at((0.5, 0.25), 8, 6) == (1, 4)


def test_pca_of_a_large_view_is_fitted_on_a_subset_and_matches_the_full_fit():
    from cusgs_jax.eval.feature_metrics import pca_rgb
    from cusgs_jax.view.modes import PCA_FIT_PIXELS

    rng = np.random.default_rng(0)
    h, w, d = 240, 320, 24
    assert h * w > PCA_FIT_PIXELS
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    basis = rng.normal(size=(3, d))
    features = (np.stack([xx, yy, xx * yy], -1) @ basis + 0.01 * rng.normal(size=(h, w, d))).astype(np.float32)
    fast, full = pca_colours(features, None).astype(int), pca_rgb([features])[0].astype(int)
    close = np.abs(fast - full) <= 3  # the basis of 8192 strided pixels ≈ that of all 76,800
    assert close.mean() > 0.99
