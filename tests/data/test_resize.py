"""Resizing feature maps (cusgs_jax.data.resize): area and nearest, zero vectors = no target."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.data.resize import resize_features
from cusgs_jax.testing.scenes import feature_maps


def test_resize_identity_and_shapes():
    maps = feature_maps()
    np.testing.assert_array_equal(resize_features(maps, (7, 5)), maps)
    assert resize_features(maps, (3, 2)).shape == (3, 2, 3, 4)
    assert resize_features(maps[0], (14, 10)).shape == (10, 14, 4)
    assert resize_features(maps, (3, 2), method="nearest").dtype == np.float32
    with pytest.raises(ValueError, match="method"):
        resize_features(maps, (3, 2), method="bicubic")
    with pytest.raises(ValueError, match="size"):
        resize_features(maps, (0, 2))


def test_resize_area_is_block_mean_for_integer_factors():
    rng = np.random.default_rng(1)
    maps = rng.uniform(0.5, 1.0, size=(2, 6, 8, 3)).astype(np.float32)
    out = resize_features(maps, (4, 3))
    expected = maps.reshape(2, 3, 2, 4, 2, 3).mean(axis=(2, 4))
    np.testing.assert_allclose(out, expected, rtol=1e-6)


def test_resize_area_ignores_zero_vectors():
    maps = np.zeros((1, 2, 2, 2), np.float32)
    maps[0, 0, 0] = [1.0, 2.0]
    out = resize_features(maps, (1, 1))
    np.testing.assert_allclose(out[0, 0, 0], [1.0, 2.0])  # not diluted by the 3 empty pixels
    empty = resize_features(np.zeros((1, 4, 4, 2), np.float32), (2, 2))
    assert not empty.any()


def test_resize_area_non_integer_factor_preserves_constants_and_mean():
    maps = np.full((1, 5, 7, 2), 3.0, np.float32)
    np.testing.assert_allclose(resize_features(maps, (3, 4)), 3.0, rtol=1e-6)
    rng = np.random.default_rng(2)
    maps = rng.uniform(1, 2, size=(1, 6, 9, 1)).astype(np.float32)
    out = resize_features(maps, (6, 4))  # 9→6, 6→4: equal-area cells, so the mean is kept
    np.testing.assert_allclose(out.mean(), maps.mean(), rtol=1e-5)


def test_resize_nearest_keeps_vectors_exactly():
    rng = np.random.default_rng(3)
    maps = rng.normal(size=(1, 4, 6, 3)).astype(np.float32)
    up = resize_features(maps, (12, 8), method="nearest")
    np.testing.assert_array_equal(up, np.repeat(np.repeat(maps, 2, axis=1), 2, axis=2))
    down = resize_features(up, (6, 4), method="nearest")
    np.testing.assert_array_equal(down, maps)
