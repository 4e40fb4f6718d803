"""Rendering a model for evaluation (training/render.py): make_render_fn / make_feature_render_fn."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, FeatureModelConfig
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.model.anchors import compact
from cusgs_jax.model.decode import decode_view, gather_visible, view_inputs
from cusgs_jax.splat import rasterize
from cusgs_jax.model.field import retrieve
from cusgs_jax.training.capacity import Capacities
from cusgs_jax.training.render import (decode_view_inputs, make_feature_render_fn, make_render_fn,
                                       render_gaussians, render_model, view_work)
from cusgs_jax.training.state import init_train_state
from cusgs_jax.types import Camera
from cusgs_jax.testing.scenes import random_banks, sfm_points

W, H = 32, 24
CAMERA = Camera(jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]), jnp.eye(4), W, H)
CFG = Config().replace(train=dict(iterations=10),
                       model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8))
FEATURES = dict(models=(FeatureModelConfig("a", query_dim=4), FeatureModelConfig("b", query_dim=6)), hidden=8)


def _banks():
    return {name: jnp.asarray(b) for name, b in random_banks({"a": (5, 3), "b": (7, 2)}).items()}


def _state(cfg, banks=None):
    state, _ = init_train_state(cfg, sfm_points(), 2, 2.0, make_strategies(cfg), banks)
    # non-zero latents and offsets, and a third of the anchors dead (as after pruning)
    key = jax.random.PRNGKey(3)
    params = state.anchors.params
    params = dataclasses.replace(params, latent=jax.random.normal(key, params.latent.shape),
                                 offsets=0.3 * jax.random.normal(jax.random.fold_in(key, 1), params.offsets.shape))
    alive = np.array(state.anchors.alive)
    alive[np.flatnonzero(alive)[::3]] = False
    return state.replace(anchors=state.anchors.replace(params=params, alive=jnp.asarray(alive)))


@pytest.mark.slow
def test_evaluation_renders_size_their_capacities_by_the_first_view_or_take_given_ones():
    state = _state(CFG)
    anchors = compact(state.anchors)
    render = make_render_fn(CFG)
    assert render.capacities is None  # nothing sized before a view is seen
    render(anchors, state.nets, CAMERA, jnp.int32(1))
    work = jax.device_get(view_work(anchors, state.nets, CAMERA, jnp.int32(1), CFG))
    caps, n = render.capacities, CFG.model.n_offsets
    assert render.growths == 0 and caps.visible_slots(anchors.capacity) >= work["visible_anchors"]
    assert caps.active_gaussians(anchors.capacity, n) >= work["active_gaussians"]
    assert caps.pairs(anchors.capacity, n) >= work["pairs"]
    given = Capacities(visible_fraction=1.0, active_fraction=0.75, pairs_per_active=9.0)
    assert make_render_fn(CFG, given).capacities == given


@pytest.mark.slow
def test_compact_render_equals_the_full_model_and_the_direct_path():
    state = _state(CFG)
    render = make_render_fn(CFG)
    anchors = compact(state.anchors)
    assert anchors.capacity < state.anchors.capacity
    (image,) = render(anchors, state.nets, CAMERA, jnp.int32(1))
    image = np.asarray(image)
    assert image.shape == (H, W, 3)
    assert image.min() >= 0.0 and image.max() <= 1.0 and image.std() > 0.01  # something was drawn
    (full,) = render(state.anchors, state.nets, CAMERA, jnp.int32(1))
    np.testing.assert_allclose(np.asarray(full), image, atol=1e-6)
    # the train step's path at visible_fraction < 1 (no visible anchor dropped here) agrees
    out, _, work = render_model(state.anchors, state.nets, CAMERA, jnp.int32(1), CFG, Capacities.from_config(CFG))
    assert int(work["dropped_anchors"]) == int(work["dropped_gaussians"]) == int(work["dropped_pairs"]) == 0
    np.testing.assert_allclose(np.clip(np.asarray(out.image), 0, 1), image, atol=1e-6)
    # and so does rasterising every decoded Gaussian without compaction (masked ones are culled)
    gaussians, view = decode_view(state.nets, state.anchors, CAMERA, jnp.int32(1), CFG.model, state.anchors.capacity)
    plain = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
                      CAMERA.world_to_camera, CAMERA.K, W, H, tile_size=CFG.splat.tile_size)
    np.testing.assert_allclose(np.clip(np.asarray(plain.image), 0, 1), image, atol=1e-6)
    # the appearance embedding matters
    (other,) = render(anchors, state.nets, CAMERA, jnp.int32(0))
    assert not np.allclose(np.asarray(other), image)


@pytest.mark.parametrize("granularity", ["per_anchor", "per_gaussian"])
def test_feature_render_matches_rgb_and_retrieves_every_model(granularity):
    cfg = CFG.replace(features=FEATURES, model=dict(query_granularity=granularity))
    banks = _banks()
    state = _state(cfg, banks)
    anchors = compact(state.anchors)
    rgb, features = make_feature_render_fn(cfg)(anchors, state.nets, CAMERA, jnp.int32(1), banks)
    (image,) = make_render_fn(cfg)(anchors, state.nets, CAMERA, jnp.int32(1))
    np.testing.assert_allclose(np.asarray(rgb), np.asarray(image), atol=1e-6)  # extra channels leave RGB alone
    assert set(features) == {"a", "b"}
    assert features["a"].shape == (H, W, 3) and features["b"].shape == (H, W, 2)
    # the features are the memory read-out of the composited queries (eager vs jitted: float32 rounding)
    gaussians, view = decode_view(state.nets, anchors, CAMERA, jnp.int32(1), cfg.model, anchors.capacity)
    inputs = view_inputs(state.nets, *gather_visible(anchors, view), CAMERA, jnp.int32(1), cfg.model)
    _, queries = decode_view_inputs(state.nets, inputs, cfg, queries=True)
    assert queries.shape == (gaussians.means.shape[0], 10)
    rendered = render_gaussians(gaussians, CAMERA, cfg.splat, extra_channels=queries)[0].image[..., 3:]
    expected = retrieve(state.nets["memory"], banks, rendered, cfg.features)
    for name in ("a", "b"):
        assert np.all(np.isfinite(np.asarray(features[name])))
        np.testing.assert_allclose(np.asarray(features[name]), np.asarray(expected[name]), atol=1e-5)


def test_gaussian_and_query_heads_read_one_input_bundle():
    """decode_view_inputs decodes the Gaussians decode_view decodes, and a change of the bundle's view
    direction reaches the Gaussians' colours and the queries alike (one source, no second copy)."""
    cfg = CFG.replace(features=FEATURES)
    state = _state(cfg, _banks())
    anchors = compact(state.anchors)
    want, view = decode_view(state.nets, anchors, CAMERA, jnp.int32(1), cfg.model, anchors.capacity)
    inputs = view_inputs(state.nets, *gather_visible(anchors, view), CAMERA, jnp.int32(1), cfg.model)
    gaussians, queries = decode_view_inputs(state.nets, inputs, cfg, queries=True)
    np.testing.assert_array_equal(np.asarray(gaussians.colors), np.asarray(want.colors))
    turned = dataclasses.replace(inputs, direction=-inputs.direction)
    gaussians2, queries2 = decode_view_inputs(state.nets, turned, cfg, queries=True)
    assert np.abs(np.asarray(gaussians2.colors - gaussians.colors)).max() > 1e-3
    assert np.abs(np.asarray(queries2 - queries)).max() > 1e-3
    np.testing.assert_array_equal(np.asarray(gaussians2.means), np.asarray(gaussians.means))  # positions ignore d


@pytest.mark.slow
def test_a_render_that_would_drop_tile_pairs_grows_its_capacity_and_is_exact(monkeypatch):
    from cusgs_jax.training import capacity

    monkeypatch.setattr(capacity, "PAIR_SLACK", 0)  # the fixed slack alone holds this tiny view's pairs
    state = _state(CFG)
    anchors = compact(state.anchors)
    (exact,) = make_render_fn(CFG)(anchors, state.nets, CAMERA, jnp.int32(1))
    tight = make_render_fn(CFG, Capacities(visible_fraction=1.0, active_fraction=0.05, pairs_per_active=0.01))
    # the first capacities cannot hold this view's Gaussians and pairs: the raw jitted render would drop some
    raw = tight.build(tight.capacities)(anchors, state.nets, CAMERA, jnp.int32(1))
    assert int(raw[-1]["dropped_gaussians"]) > 0
    (image,) = tight(anchors, state.nets, CAMERA, jnp.int32(1))
    assert tight.growths >= 2 and tight.capacities.pairs_per_active > 0.01
    assert tight.capacities.active_fraction > 0.05
    np.testing.assert_allclose(np.asarray(image), np.asarray(exact), atol=1e-6)
