"""Loss terms of one's own (training/loss_terms.py) in the jitted step (training/step.py): checked on entry, added
with their weight as a program argument, differentiated, reported weighted beside the built-in terms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.testing.scenes import sfm_points
from cusgs_jax.training.loss_terms import (BUILT_IN_TERMS, LossTally, LossTerm, check_loss_terms, term_weights,
                                          weighted_terms)
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import loss_weights, make_train_step, step_settings
from cusgs_jax.types import Camera

W, H = 32, 24
K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])


def mean_alpha(render, batch, state):
    """A term of the render only: the mean accumulated opacity."""
    del batch, state
    return jnp.mean(render.alpha)


def depth_tv(render, batch, state):
    del batch, state
    depth = render.depth / jnp.maximum(render.alpha, 1e-3)
    return jnp.mean(jnp.abs(jnp.diff(depth, axis=0))) + jnp.mean(jnp.abs(jnp.diff(depth, axis=1)))


def _cfg():
    return Config().replace(train=dict(iterations=50),
                            model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
                            prune=dict(strategy="none"))


def _batch(terms=()):
    rng = np.random.default_rng(0)
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = rng.normal(0, 0.05, 3)
    cfg = _cfg()
    return dict(image=jnp.asarray(rng.uniform(0, 1, (H, W, 3)).astype(np.float32)),
                camera=Camera(K, jnp.asarray(view), W, H), index=jnp.int32(0),
                **step_settings(cfg, 2.0, terms))


@pytest.fixture(scope="module")
def model():
    cfg = _cfg()
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies)
    return cfg, strategies, state, tx


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)


def test_terms_are_checked_on_entry():
    ok = LossTerm("depth_tv", depth_tv, 0.5)
    assert check_loss_terms([ok]) == (ok,) and check_loss_terms(None) == ()
    assert term_weights([ok]) == {"depth_tv": np.float32(0.5)}
    bad = [([depth_tv], TypeError, "is not a LossTerm"), ([LossTerm("l1", depth_tv)], ValueError, "already taken"),
           ([ok, ok], ValueError, "already taken"), ([LossTerm("depth tv", depth_tv)], ValueError, "identifier"),
           ([LossTerm("x", 3.0)], TypeError, "not callable"), ([LossTerm("x", depth_tv, -1.0)], ValueError, ">= 0"),
           ([LossTerm("x", depth_tv, float("nan"))], ValueError, ">= 0"), ([LossTerm("x", depth_tv, "a")], ValueError,
                                                                              ">= 0")]
    for terms, error, text in bad:
        with pytest.raises(error, match=text):
            check_loss_terms(terms)
    for name in BUILT_IN_TERMS:
        with pytest.raises(ValueError, match="already taken"):
            check_loss_terms([LossTerm(name, depth_tv)])


def test_every_term_is_reported_weighted_and_they_sum_to_the_loss(model):
    cfg, strategies, state, tx = model
    terms = (LossTerm("mean_alpha", mean_alpha, 0.3), LossTerm("depth_tv", depth_tv, 0.05))
    step = make_train_step(cfg, tx, strategies, loss_terms=terms)
    _, metrics = step(_copy(state), _batch(terms))
    weighted = weighted_terms(jax.device_get(metrics), loss_weights(cfg, terms))
    assert set(weighted) == {"l1", "ssim", "volume", "mean_alpha", "depth_tv"}
    np.testing.assert_allclose(sum(weighted.values()), float(metrics["loss"]), rtol=1e-6)
    np.testing.assert_allclose(weighted["mean_alpha"], 0.3 * float(metrics["loss_mean_alpha"]), rtol=1e-6)
    assert 0 < float(metrics["loss_mean_alpha"]) <= 1
    np.testing.assert_allclose(weighted["l1"], cfg.loss.l1_weight * float(metrics["loss_l1"]), rtol=1e-6)
    np.testing.assert_allclose(weighted["ssim"], cfg.loss.ssim_weight * (1 - float(metrics["loss_ssim"])), rtol=1e-6)


def test_the_weight_is_an_argument_of_the_program_and_the_term_is_differentiated(model, compiles):
    """Two weights: one compiled step; the loss moves by Δweight · term; the update follows the term's gradient
    (a term that pushes opacity down changes the parameters differently from the built-in loss alone)."""
    cfg, strategies, state, tx = model
    terms = (LossTerm("mean_alpha", mean_alpha, 1.0),)
    step = make_train_step(cfg, tx, strategies, loss_terms=terms)
    plain = make_train_step(cfg, tx, strategies)
    batch = _batch(terms)
    light = dict(batch, loss_weights=dict(batch["loss_weights"], mean_alpha=jnp.float32(0.0)))
    heavy = dict(batch, loss_weights=dict(batch["loss_weights"], mean_alpha=jnp.float32(10.0)))
    new_light, m_light = step(_copy(state), light)
    new_heavy, m_heavy = step(_copy(state), heavy)
    assert compiles.count("jit(train_step)") == 1
    value = float(m_light["loss_mean_alpha"])
    np.testing.assert_allclose(float(m_heavy["loss"]) - float(m_light["loss"]), 10.0 * value, rtol=1e-5)
    # weight 0: the same update as the step without the term (bit for bit)
    new_plain, m_plain = plain(_copy(state), {k: v for k, v in batch.items() if k != "loss_weights"})
    assert float(m_plain["loss"]) == float(m_light["loss"])
    for a, b in zip(jax.tree_util.tree_leaves(new_plain.trainable), jax.tree_util.tree_leaves(new_light.trainable)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    moved = [float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree_util.tree_leaves(new_heavy.trainable),
                                                            jax.tree_util.tree_leaves(new_light.trainable))]
    assert max(moved) > 0


def test_a_term_that_is_not_finite_skips_the_update(model):
    cfg, strategies, state, tx = model
    terms = (LossTerm("broken", lambda render, batch, state: jnp.log(-jnp.mean(render.alpha) - 1.0), 1.0),)
    new, metrics = make_train_step(cfg, tx, strategies, loss_terms=terms)(_copy(state), _batch(terms))
    assert not bool(metrics["finite"]) and int(new.skipped) == 1


def test_the_tally_sums_every_step_and_round_trips_through_a_checkpoint_record():
    tally = LossTally()
    tally.add({"l1": np.float32(0.5), "depth_tv": 0.25})
    tally.add({"l1": 0.25, "depth_tv": 0.25})
    record = tally.as_dict()
    assert record == {"steps": 2, "sum": {"l1": 0.75, "depth_tv": 0.5}, "mean": {"l1": 0.375, "depth_tv": 0.25}}
    again = LossTally.restored(record)
    assert again.as_dict() == record and LossTally.restored(None).as_dict()["steps"] == 0
