"""What a run reads (app/inputs.py): feature targets keep every value float16 cannot hold."""

from __future__ import annotations

import numpy as np

from cusgs_jax.app.inputs import FLOAT16_MAX, feature_targets


class _Maps:
    def __init__(self, maps):
        self.maps = maps


def test_feature_targets_are_float16_unless_a_value_would_overflow_it():
    small = np.random.default_rng(0).normal(size=(3, 4, 5, 2)).astype(np.float32)
    large = small.copy()
    large[1, 2, 3, 0] = 1e5  # beyond float16's 65504: would become inf
    targets = feature_targets({"small": _Maps(small), "large": _Maps(large)}, np.array([0, 1]))
    assert targets["small"].dtype == np.float16 and targets["large"].dtype == np.float32
    assert np.all(np.isfinite(np.asarray(targets["large"]))) and float(np.max(targets["large"])) == 1e5
    np.testing.assert_array_equal(np.asarray(targets["large"]), large[[0, 1]])
    assert FLOAT16_MAX == 65504.0
