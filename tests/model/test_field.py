"""Feature field read-out: memory retrieval, the feature loss, and paying only for what a scene uses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import FeatureConfig, FeatureModelConfig
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.memory.attention import attend, precompute_keys
from cusgs_jax.model.field import (feature_loss, init_memory_heads, retrieve, sampled_feature_loss,
                                   stratified_pixels)
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step


def test_feature_loss_masks_invalid_pixels():
    pred = jnp.array([[1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    target = jnp.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    loss, terms = feature_loss(pred, target, jnp.array([True, True, False]))
    np.testing.assert_allclose(terms["l2"], (0.0 + 1.0) / 2)
    np.testing.assert_allclose(terms["cos"], (0.0 + 1.0) / 2)
    np.testing.assert_allclose(loss, 1.0)


def test_m3_query_split_when_dims_are_not_given():
    cfg = FeatureConfig(models=tuple(FeatureModelConfig(n) for n in ("clip", "siglip", "dinov2", "seem",
                                                                     "llama3", "llamav")))
    assert cfg.query_dim == 160 and [m.query_dim for m in cfg.models] == [16, 32, 32, 16, 32, 32]
    assert [(s.start, s.stop) for _, s in cfg.slices()] == [(0, 16), (16, 48), (48, 80), (80, 96), (96, 128),
                                                            (128, 160)]


def _heads(cfg, banks):
    """Memory heads, initialised in one compiled program (eager random draws compile one by one)."""
    return jax.jit(init_memory_heads, static_argnums=1)(jax.random.PRNGKey(0), cfg, banks)


def test_retrieve_reads_each_models_slice(feature_scene):
    cfg = FeatureConfig(models=feature_scene.models)
    banks = feature_scene.banks()
    heads = _heads(cfg, banks)
    assert {k: v["key_proj"].shape for k, v in heads.items()} == {"alpha": (17, 6), "beta": (20, 9)}
    queries = jnp.asarray(np.random.default_rng(0).normal(size=(3, 5, 37)), jnp.float32)

    @jax.jit
    def run(heads, banks, queries):
        out = retrieve(heads, banks, queries, cfg)
        want = {name: attend(heads[name], queries[..., sl], precompute_keys(heads[name], banks[name]), banks[name])
                for name, sl in (("alpha", slice(0, 17)), ("beta", slice(17, 37)))}
        # the other model's channels do not matter
        scrambled = retrieve(heads, banks, queries.at[..., 17:].set(7.0), cfg)["alpha"]
        return out, want, scrambled

    out, want, scrambled = run(heads, banks, queries)
    assert out["alpha"].shape == (3, 5, 6) and out["beta"].shape == (3, 5, 9)
    for name in ("alpha", "beta"):
        np.testing.assert_allclose(out[name], want[name], rtol=1e-6)
    np.testing.assert_allclose(scrambled, out["alpha"], rtol=1e-6)


def test_sampled_feature_loss_reads_the_nearest_image_pixel(feature_scene):
    """All pixels (sample_pixels = 0) of a half-resolution target: the loss of the queries at the pixel
    centres nearest to each feature pixel, summed over models."""
    cfg = FeatureConfig(models=feature_scene.models, sample_pixels=0)
    banks = feature_scene.banks()
    heads = _heads(cfg, banks)
    rng = np.random.default_rng(4)
    queries = jnp.asarray(rng.normal(size=(6, 8, 37)), jnp.float32)
    beta = rng.normal(size=(3, 4, 9))
    beta[0, 0] = 0.0  # no target there
    targets = {"alpha": jnp.asarray(rng.normal(size=(6, 8, 6)), jnp.float32), "beta": jnp.asarray(beta, jnp.float32)}

    @jax.jit
    def run(queries, targets, heads, banks):
        total, terms = sampled_feature_loss(queries, targets, heads, banks, jax.random.PRNGKey(0), cfg)
        want = {}
        for name, sl, picked in (("alpha", slice(0, 17), queries),
                                 ("beta", slice(17, 37), queries[1::2, 1::2])):  # (r + 0.5) · 2 → rows 1, 3, 5
            q = picked[..., sl].reshape(-1, sl.stop - sl.start)
            t = targets[name].reshape(-1, targets[name].shape[-1])
            pred = attend(heads[name], q, precompute_keys(heads[name], banks[name]), banks[name])
            want[name] = feature_loss(pred, t, jnp.any(t != 0, axis=-1))
        return total, terms, want

    total, terms, want = run(queries, targets, heads, banks)
    for name, (_, parts) in want.items():
        np.testing.assert_allclose(terms[f"feat_{name}_l2"], parts["l2"], rtol=1e-5)
        np.testing.assert_allclose(terms[f"feat_{name}_cos"], parts["cos"], rtol=1e-5)
    np.testing.assert_allclose(total, sum(float(loss) for loss, _ in want.values()), rtol=1e-5)


@pytest.mark.parametrize("total, count", [(96, 10), (19200, 2000), (7, 7)])
def test_stratified_pixels_draw_one_per_stratum_and_every_pixel_equally_often(total, count):
    draws = np.asarray(jax.jit(jax.vmap(lambda k: stratified_pixels(k, total, count)))(
        jax.random.split(jax.random.PRNGKey(3), 4000)))
    assert draws.shape == (4000, count) and draws.min() >= 0 and draws.max() < total
    # draw i lies in stratum i: pixels [floor(i·total/count), floor(((i+1)·total − 1)/count)]
    i = np.arange(count)
    assert np.all(draws >= (i * total) // count) and np.all(draws <= ((i + 1) * total - 1) // count)
    assert np.mean(np.diff(draws, axis=1) > 0) > 0.9  # in order, and a repeat only at a shared boundary
    # every pixel is drawn with probability count / total (a binomial count per pixel, 5 sigma)
    hits = np.bincount(draws.ravel(), minlength=total) / 4000
    p = count / total
    assert np.all(np.abs(hits - p) < 5 * np.sqrt(p * (1 - p) / 4000) + 1e-9)
    if count == total:
        np.testing.assert_array_equal(draws, np.broadcast_to(i, draws.shape))


def test_scene_without_features_traces_no_feature_work(feature_scene):
    for enabled in (False, True):
        cfg = feature_scene.cfg(features=enabled)
        strategies = make_strategies(cfg)
        state, tx = init_train_state(cfg, feature_scene.points(), 1, 2.0, strategies,
                                     banks=feature_scene.banks() if enabled else None)
        assert ("queries" in state.nets) == enabled and ("memory" in state.nets) == enabled
        step = make_train_step(cfg, tx, strategies)
        text = str(jax.make_jaxpr(step)(state, feature_scene.batch(enabled)))
        has_query_channels = ",40]" in text  # 3 RGB + 37 query channels composited together
        has_bank = "[23," in text  # memory entries enter the attention
        assert has_query_channels == enabled and has_bank == enabled, enabled


@pytest.mark.slow
def test_feature_training_step_runs_and_learns(feature_scene, compiles):
    # every pixel in the loss (sample_pixels = 0), so the loss is a function of the parameters alone and the
    # curve is not sampling noise
    cfg = feature_scene.cfg().replace(features=dict(sample_pixels=0))
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, feature_scene.points(), 1, 2.0, strategies, banks=feature_scene.banks())
    step = make_train_step(cfg, tx, strategies)
    batch = feature_scene.batch()
    losses = []
    for _ in range(15):
        state, metrics = step(state, batch)
        losses.append(float(metrics["loss_feature"]))
    assert bool(metrics["finite"]) and np.all(np.isfinite(losses))
    # measured: 3.770 -> 3.382 (0.897×), falling at 13 of 14 steps
    assert losses[-1] < 0.93 * losses[0], losses
    assert np.mean(np.diff(losses) < 0) > 0.8, losses  # falling at (almost) every step
    assert compiles.count("jit(train_step)") == 1
