"""The viewer's model and render without a browser: a trained run's frame equals the library render at the same
camera; view_model centres on the alive anchors with the mean appearance; the scene's camera list."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def trained(feature_run):
    from cusgs_jax.io.load_run import load_trained

    return load_trained(feature_run)


@pytest.mark.slow
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


def test_view_model_centres_on_the_alive_anchors_and_averages_the_appearance(trained):
    import dataclasses

    import jax

    from cusgs_jax.view.render import view_model

    anchors = trained.anchors
    alive = np.asarray(anchors.alive)
    assert not alive.all()  # compacted to a multiple of 64: dead padding slots that must not move the centre
    model = view_model(trained.cfg, anchors, trained.nets, trained.banks, [])
    np.testing.assert_allclose(model.center, np.asarray(anchors.centers)[alive].mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(model.nets["appearance"]),
                               np.asarray(trained.nets["appearance"]).mean(axis=0, keepdims=True), rtol=1e-6)
    assert model.nets["decoder"] is trained.nets["decoder"] and model.anchors is anchors
    assert set(model.banks) == {"semantic"} and isinstance(model.banks["semantic"], jax.Array)
    assert model.cameras == [] and model.up.tolist() == [0.0, -1.0, 0.0]  # no camera: the OpenCV default up
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.banks = None


def test_scene_cameras_list_the_training_views_then_the_held_out_ones(demo):
    from cusgs_jax.config import DataConfig
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.view.render import scene_cameras

    # views 0 and 2 held out: the lists interleave in the scene
    scene = load_scene(demo, DataConfig(format="colmap", holdout_every=2))
    train, held_out = scene.train_indices, scene.test_indices
    assert len(train) and len(held_out)
    cameras = scene_cameras(scene, train)
    assert [c[0] for c in cameras] == ([f"train {i}" for i in range(len(train))]
                                       + [f"held-out {i}" for i in range(len(held_out))])
    for (_, K, viewmat, width, height), view in zip(cameras, [*train, *held_out]):
        np.testing.assert_array_equal(K, scene.Ks[view])
        np.testing.assert_array_equal(viewmat, scene.viewmats[view])
        assert (width, height) == (scene.width, scene.height)
