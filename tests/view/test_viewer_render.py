"""The viewer's render without a browser: a trained run's frame equals the library render at the same camera."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def trained(feature_run):
    from cusgs_jax.io.load_run import load_trained

    return load_trained(feature_run)


def test_frame_equals_the_library_render_with_the_mean_appearance(trained):
    import jax.numpy as jnp

    from cusgs_jax.training.render import make_feature_render_fn
    from cusgs_jax.types import Camera
    from cusgs_jax.view.render import ViewRenderer, from_trained

    model = from_trained(trained)
    label, K, viewmat, width, height = model.cameras[0]
    camera = Camera(jnp.asarray(K), jnp.asarray(viewmat), width, height)

    frame = ViewRenderer(model.cfg).render(model, camera, features=True)

    assert frame.rgb.shape == (height, width, 3) and frame.alpha.shape == (height, width)
    assert set(frame.features) == set(model.feature_models) and model.feature_models
    # The library render with index 0 of the mean-appearance networks is the same picture.
    rgb, features = make_feature_render_fn(model.cfg)(model.anchors, model.nets, camera, jnp.int32(0), model.banks)
    np.testing.assert_allclose(frame.rgb, np.asarray(rgb), atol=1e-5)
    for name in model.feature_models:
        np.testing.assert_allclose(frame.features[name], np.asarray(features[name]), atol=1e-5)
    assert frame.alpha.max() > 0.5  # the model covers the view: not an empty frame


def test_rgb_only_frame_has_no_features(trained):
    import jax.numpy as jnp

    from cusgs_jax.types import Camera
    from cusgs_jax.view.render import ViewRenderer, from_trained

    model = from_trained(trained)
    label, K, viewmat, width, height = model.cameras[-1]

    frame = ViewRenderer(model.cfg).render(model, Camera(jnp.asarray(K), jnp.asarray(viewmat), width, height))
    assert frame.features == {} and np.isfinite(frame.rgb).all() and np.isfinite(frame.depth).all()
