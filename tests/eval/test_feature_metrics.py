"""Tests of the host-side feature-field evaluation (cusgs_jax.eval.feature_metrics)."""

from __future__ import annotations

import warnings

import imageio.v3 as iio
import numpy as np
import pytest

from cusgs_jax.eval import feature_metrics as fe

# --------------------------------------------------------------------------------------------
# feature_errors / baseline
# --------------------------------------------------------------------------------------------


def _rand(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape).astype(np.float32)


def test_identical_features_give_zero_errors():
    t = _rand((2, 5, 6, 8))
    out = fe.feature_errors(t, t.copy(), np.ones((2, 5, 6), bool))
    assert out["cosine"] == pytest.approx(0.0, abs=1e-7)
    assert out["l2"] == 0.0
    assert out["num_valid"] == 60 and out["num_valid_per_view"] == [30, 30]
    np.testing.assert_allclose(out["cosine_per_view"], 0.0, atol=1e-7)
    assert out["l2_per_view"] == [0.0, 0.0]


def test_opposite_features_give_cosine_distance_two():
    t = _rand((1, 4, 4, 5), seed=1)
    out = fe.feature_errors(-t, t, None)
    assert out["cosine"] == pytest.approx(2.0, abs=1e-7)
    expected_l2 = np.mean(2.0 * np.linalg.norm(t.astype(np.float64), axis=-1))
    assert out["l2"] == pytest.approx(expected_l2, rel=1e-6)


def test_closed_form_values_and_scale_invariance_of_cosine():
    # pred (1, 0) vs target (0, 2): cos 0 → distance 1, L2 = √5.
    # pred (3, 4) vs target (6, 8): cos 1 → distance 0, L2 = 5.
    pred = np.array([[[[1.0, 0.0], [3.0, 4.0]]]])
    target = np.array([[[[0.0, 2.0], [6.0, 8.0]]]])
    out = fe.feature_errors(pred, target)
    assert out["cosine"] == pytest.approx(0.5)
    assert out["l2"] == pytest.approx((np.sqrt(5.0) + 5.0) / 2)


def test_invalid_pixels_are_ignored_and_views_pool_by_pixel_count():
    t = _rand((2, 4, 4, 3), seed=2)
    p = t.copy()
    valid = np.zeros((2, 4, 4), bool)
    valid[0, :2] = True  # 8 valid pixels in view 0
    valid[1, 0, 0] = True  # 1 valid pixel in view 1
    p[~valid] = 1e6 * _rand((int((~valid).sum()), 3), seed=3)  # garbage where invalid
    assert fe.feature_errors(p, t, valid)["l2"] == 0.0

    p[1, 0, 0] = -t[1, 0, 0]  # one wrong pixel in view 1
    out = fe.feature_errors(p, t, valid)
    assert out["cosine_per_view"][0] == pytest.approx(0.0, abs=1e-7)
    assert out["cosine_per_view"][1] == pytest.approx(2.0)
    assert out["cosine"] == pytest.approx(2.0 / 9.0)  # pooled over the 9 pixels, not (0 + 2) / 2
    assert out["num_valid_per_view"] == [8, 1]


def test_zero_vectors_are_safe():
    pred = np.zeros((1, 2, 2, 4))
    target = np.zeros((1, 2, 2, 4))
    target[0, 0, 0] = [1.0, 2.0, 2.0, 0.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no divide-by-zero / invalid warnings
        out = fe.feature_errors(pred, target, None)
    assert np.isfinite(out["cosine"]) and out["cosine"] == pytest.approx(1.0)
    assert out["l2"] == pytest.approx(3.0 / 4.0)


def test_view_without_valid_pixels_is_nan_and_shape_mismatch_raises():
    t = _rand((2, 3, 3, 2))
    valid = np.zeros((2, 3, 3), bool)
    valid[0] = True
    out = fe.feature_errors(t, t, valid)
    assert np.isnan(out["cosine_per_view"][1]) and np.isnan(out["l2_per_view"][1])
    assert out["l2"] == 0.0
    with pytest.raises(ValueError, match="resize_to"):
        fe.feature_errors(t[:, :2], t, None)


def test_mean_feature_baseline_matches_hand_computation():
    targets = np.zeros((2, 1, 2, 2))
    targets[0, 0, 0] = [1.0, 0.0]
    targets[0, 0, 1] = [3.0, 2.0]
    targets[1, 0, 0] = [2.0, 4.0]
    targets[1, 0, 1] = [100.0, 100.0]  # invalid
    valid = np.array([[[True, True]], [[True, False]]])
    mean = fe.mean_feature_baseline(targets, valid)
    np.testing.assert_allclose(mean, [2.0, 2.0])

    out = fe.baseline_errors(mean, targets, valid)
    # (2,2) vs (1,0): cos = 2/(√8·1) = 1/√2, L2 = √5
    # (2,2) vs (3,2): cos = 10/(√8·√13),    L2 = 1
    # (2,2) vs (2,4): cos = 12/(√8·√20),    L2 = 2
    cos = np.array([1 / np.sqrt(2), 10 / np.sqrt(8 * 13), 12 / np.sqrt(8 * 20)])
    assert out["cosine"] == pytest.approx(np.mean(1 - cos))
    assert out["l2"] == pytest.approx((np.sqrt(5) + 1 + 2) / 3)
    with pytest.raises(ValueError):
        fe.mean_feature_baseline(targets, np.zeros((2, 1, 2), bool))


# --------------------------------------------------------------------------------------------
# resize_to
# --------------------------------------------------------------------------------------------


def test_resize_identity_and_block_mean():
    maps = _rand((2, 4, 6, 3), seed=4)
    assert fe.resize_to(maps, (4, 6)) is maps  # same size: unchanged, no copy
    np.testing.assert_array_equal(fe.resize_to(maps, (4, 6)), maps)

    small = fe.resize_to(maps, (2, 3))
    assert small.shape == (2, 2, 3, 3)
    np.testing.assert_allclose(small[1, 1, 2], maps[1, 2:4, 4:6].mean(axis=(0, 1)), rtol=1e-6)
    np.testing.assert_allclose(small[0, 0, 0], maps[0, :2, :2].mean(axis=(0, 1)), rtol=1e-6)
    # [H, W, D] input works too
    np.testing.assert_allclose(fe.resize_to(maps[0], (2, 3)), small[0], rtol=1e-6)


def test_resize_non_divisible_uses_skimage_and_keeps_constants():
    maps = np.broadcast_to(np.array([1.0, -2.0, 0.5]), (2, 7, 9, 3)).copy()
    maps[1] *= 3.0
    out = fe.resize_to(maps, (3, 4))
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(out[0], np.broadcast_to([1.0, -2.0, 0.5], (3, 4, 3)), atol=1e-6)
    np.testing.assert_allclose(out[1], np.broadcast_to([3.0, -6.0, 1.5], (3, 4, 3)), atol=1e-6)
    # views and channels stay independent: a ramp along x in one channel only
    ramp = np.zeros((1, 8, 10, 2))
    ramp[0, :, :, 1] = np.arange(10)[None, :]
    r = fe.resize_to(ramp, (3, 4))
    np.testing.assert_allclose(r[..., 0], 0.0, atol=1e-12)
    assert np.all(np.diff(r[0, 1, :, 1]) > 0)


# --------------------------------------------------------------------------------------------
# Retrieval
# --------------------------------------------------------------------------------------------


def _object_scene():
    """3 views of 16×20 pixels, objects 1..4 (different sizes, moving a little between views),
    features = one-hot of the object id (index 0 = background)."""
    n, h, w = 3, 16, 20
    ids = np.zeros((n, h, w), np.int64)
    for v in range(n):
        ids[v, 1:4, 1 + v:4 + v] = 1  # 9 px
        ids[v, 6:12, 2:8] = 2  # 36 px
        ids[v, 2:7, 12:17] = 3  # 25 px
        ids[v, 10:15, 11 + v:18] = 4
    feats = np.eye(5)[ids].astype(np.float32)  # [n, h, w, 5]
    return feats, ids


def test_retrieval_perfect_with_one_hot_features():
    feats, ids = _object_scene()
    queries = fe.object_queries(feats, ids, None)
    assert sorted(queries) == [1, 2, 3, 4]
    np.testing.assert_allclose(queries[3], np.eye(5)[3])
    out = fe.retrieval_scores(feats, ids, queries)
    assert out["per_object"] == {1: 1.0, 2: 1.0, 3: 1.0, 4: 1.0}
    assert out["mIoU"] == 1.0 and out["cIoU"] == 1.0 and out["AP50"] == 1.0
    assert out["skipped"] == []
    assert all(0.0 < t < 1.0 for t in out["thresholds"].values())
    # With noise, Otsu on the pooled (mostly background) scores puts the threshold in the upper
    # tail of the background scores, so a few background pixels get in: close, not perfect.
    noisy = feats + 0.02 * _rand(feats.shape, seed=5)
    out = fe.retrieval_scores(noisy, ids, queries)
    assert out["mIoU"] > 0.95 and out["cIoU"] > 0.95 and out["AP50"] == 1.0


def test_retrieval_swapped_objects_fail():
    feats, ids = _object_scene()
    queries = fe.object_queries(feats, ids)
    swapped = feats.copy()
    swapped[ids == 1] = np.eye(5)[2]
    swapped[ids == 2] = np.eye(5)[1]
    out = fe.retrieval_scores(swapped, ids, queries)
    assert out["per_object"] == {1: 0.0, 2: 0.0, 3: 1.0, 4: 1.0}
    assert out["mIoU"] == 0.5 and out["AP50"] == 0.5
    a = {k: int((ids == k).sum()) for k in range(1, 5)}
    expected_ciou = (a[3] + a[4]) / (2 * (a[1] + a[2]) + a[3] + a[4])
    assert out["cIoU"] == pytest.approx(expected_ciou)


def test_retrieval_one_object_takes_anothers_features():
    feats, ids = _object_scene()
    queries = fe.object_queries(feats, ids)
    merged = feats.copy()
    merged[ids == 1] = np.eye(5)[2]  # object 1 now looks like object 2
    out = fe.retrieval_scores(merged, ids, queries)
    a1, a2 = int((ids == 1).sum()), int((ids == 2).sum())
    # query 1 scores 0 everywhere → constant → empty prediction → IoU 0
    assert out["thresholds"][1] is None and out["per_object"][1] == 0.0
    # query 2 finds objects 1 ∪ 2: IoU = a2 / (a1 + a2) > 0.5 (object 1 is the smaller)
    assert out["per_object"][2] == pytest.approx(a2 / (a1 + a2))
    assert out["per_object"][2] > 0.5
    assert out["AP50"] == 0.75
    assert out["mIoU"] == pytest.approx((0 + a2 / (a1 + a2) + 1 + 1) / 4)


def test_otsu_fallback_on_constant_scores_and_skipping():
    feats, ids = _object_scene()
    const = np.ones_like(feats)  # every pixel has the same feature: scores all equal
    queries = {1: np.eye(5)[1], 7: np.eye(5)[2]}  # object 7 does not exist
    out = fe.retrieval_scores(const, ids, queries)
    assert out["thresholds"] == {1: None, 7: None}
    assert out["per_object"] == {1: 0.0}  # empty prediction vs a non-empty object
    assert out["skipped"] == [7]  # union 0: absent and not predicted
    assert out["mIoU"] == 0.0 and out["cIoU"] == 0.0 and out["AP50"] == 0.0

    none = fe.retrieval_scores(const, ids, {7: np.eye(5)[2]})
    assert none["per_object"] == {} and np.isnan(none["mIoU"]) and np.isnan(none["cIoU"])


def test_retrieval_valid_mask_and_object_queries_valid():
    feats, ids = _object_scene()
    valid = np.ones(ids.shape, bool)
    valid[0] = False  # drop view 0 entirely
    wrong = feats.copy()
    wrong[0] = np.eye(5)[1]  # view 0 garbage: all object 1
    queries = fe.object_queries(wrong, ids, valid)
    np.testing.assert_allclose(queries[2], np.eye(5)[2])  # garbage view not averaged in
    out = fe.retrieval_scores(wrong, ids, queries, valid=valid)
    assert out["mIoU"] == 1.0


# --------------------------------------------------------------------------------------------
# PCA pictures
# --------------------------------------------------------------------------------------------


def test_pca_rgb_shapes_same_basis_and_black_zeros():
    fmap = _rand((10, 12, 16), seed=6)
    fmap[0, :3] = 0.0  # three "no target" pixels
    other = _rand((5, 7, 16), seed=7)
    imgs = fe.pca_rgb([fmap, fmap.copy(), other])
    assert [im.shape for im in imgs] == [(10, 12, 3), (10, 12, 3), (5, 7, 3)]
    assert all(im.dtype == np.uint8 for im in imgs)
    np.testing.assert_array_equal(imgs[0], imgs[1])  # identical inputs → identical images
    np.testing.assert_array_equal(imgs[0][0, :3], 0)  # zeros → black
    assert imgs[0].reshape(-1, 3)[3:].max() > 0

    # same basis across maps: a vector copied into another map keeps its colour
    other[2, 3] = fmap[4, 5]
    a, b = fe.pca_rgb([fmap, other], fit_on=fmap)
    np.testing.assert_array_equal(a[4, 5], b[2, 3])
    # default fit is the first map
    np.testing.assert_array_equal(fe.pca_rgb([fmap, other])[1], b)


def test_pca_rgb_low_dimension_and_errors():
    fmap = _rand((4, 4, 2), seed=8)  # D = 2 < 3: third channel mid-grey
    (img,) = fe.pca_rgb([fmap])
    assert img.shape == (4, 4, 3)
    assert np.all(img[..., 2] == 128)
    with pytest.raises(ValueError, match="non-zero"):
        fe.pca_rgb([fmap], fit_on=np.zeros((4, 4, 2)))
    with pytest.raises(ValueError):
        fe.pca_rgb([np.zeros((4, 4, 3))], fit_on=fmap)


def test_save_feature_comparison_writes_png(tmp_path):
    target = _rand((9, 13, 8), seed=9)
    path = fe.save_feature_comparison(tmp_path / "sub" / "cmp.png", target.copy(), target)
    img = iio.imread(path)
    assert img.shape == (9, 26, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[:, :13], img[:, 13:])  # perfect prediction: equal halves
    with pytest.raises(ValueError, match="resize_to"):
        fe.save_feature_comparison(tmp_path / "x.png", target[:4], target)
