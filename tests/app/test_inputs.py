"""What a run reads (app/inputs.py): feature targets keep every value float16 cannot hold; images smaller
than the SSIM window are refused at load."""

from __future__ import annotations

import numpy as np
import pytest

from cusgs_jax.app.inputs import FLOAT16_MAX, feature_targets, load_data
from cusgs_jax.config import compose_config
from cusgs_jax.data.errors import SceneError


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


def test_images_smaller_than_the_ssim_window_are_refused_at_load_naming_the_fix(demo, tmp_path):
    from cusgs_jax.testing.scenes import object_scene

    scene, _ = load_data(compose_config([f"data.path={demo}", "data.downscale=2", "features=none"]))
    assert (scene.width, scene.height) == (20, 15)  # 40x30 / 2: large enough
    with pytest.raises(SceneError, match=r"demo.*: its images load at 10x8 pixels with data\.downscale=4, smaller "
                                         r"than the 11x11 pixels .*SSIM.*use a smaller data\.downscale "
                                         r"\(e\.g\. data\.downscale=2\)"):
        load_data(compose_config([f"data.path={demo}", "data.downscale=4", "features=none"]))
    tiny = object_scene(tmp_path / "tiny", views=4, width=8, height=8, num_points=50)
    with pytest.raises(SceneError, match=r"8x8 pixels with data\.downscale=1.*images of at least 11x11 pixels"):
        load_data(compose_config([f"data.path={tiny}", "features=none"]))
