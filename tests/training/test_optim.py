"""Per-group Adam with log-linear learning-rate decay (training/optim.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config, FeatureModelConfig, OptimConfig
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.training.optim import GROUP_OF_PATH, log_linear_schedule, make_optimizer, param_labels
from cusgs_jax.training.state import init_train_state

CFG = Config().replace(train=dict(iterations=4),
                       model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
                       features=dict(models=(FeatureModelConfig("a", query_dim=4),), hidden=8))
EXTENT = 2.5


def _trainable():
    pts = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    banks = {"a": jnp.ones((3, 5), jnp.float32)}
    state, _ = init_train_state(CFG, pts, 2, EXTENT, make_strategies(CFG), banks)
    return state.trainable


def test_log_linear_schedule_end_points_and_midpoint():
    schedule = log_linear_schedule(0.01, 0.0001, 100)
    np.testing.assert_allclose(float(schedule(0)), 0.01, rtol=1e-6)
    np.testing.assert_allclose(float(schedule(100)), 0.0001, rtol=1e-5)
    np.testing.assert_allclose(float(schedule(50)), 0.001, rtol=1e-5)  # geometric mean
    np.testing.assert_allclose(float(schedule(1000)), 0.0001, rtol=1e-5)  # clamped after the run
    values = [float(schedule(s)) for s in range(0, 101, 10)]
    assert all(a > b for a, b in zip(values, values[1:]))
    assert float(log_linear_schedule(0.3, 0.3, 10)(7)) == pytest.approx(0.3)


def test_every_parameter_has_its_group():
    trainable = _trainable()
    labels = param_labels(trainable)
    anchor = labels["anchor"]
    assert (anchor.offsets, anchor.latent, anchor.log_scaling) == ("offsets", "latent", "scaling")
    for head, group in (("opacity", "mlp_opacity"), ("cov", "mlp_cov"), ("color", "mlp_color")):
        assert set(jax.tree_util.tree_leaves(labels["decoder"][head])) == {group}
    assert labels["appearance"] == "appearance"
    assert set(jax.tree_util.tree_leaves(labels["queries"])) == {"features"}
    assert set(jax.tree_util.tree_leaves(labels["memory"])) == {"features"}
    assert set(GROUP_OF_PATH.values()) == set(OptimConfig().groups())
    with pytest.raises(KeyError, match="no optimiser group"):
        param_labels({"mystery": jnp.zeros(3)})


@pytest.mark.slow
def test_each_group_steps_with_its_own_decaying_rate():
    """With a constant unit gradient Adam's bias-corrected step is the learning rate (float32 rounding)."""
    trainable = _trainable()
    cfg = CFG.optim
    tx = make_optimizer(cfg, trainable, CFG.train.iterations, EXTENT)
    opt_state = tx.init(trainable)
    grads = jax.tree_util.tree_map(jnp.ones_like, trainable)
    seen = {"offsets": [], "latent": [], "mlp_opacity": [], "mlp_color": [], "appearance": [], "features": []}
    for _ in range(CFG.train.iterations + 1):
        updates, opt_state = tx.update(grads, opt_state, trainable)
        seen["offsets"].append(np.asarray(updates["anchor"].offsets))
        seen["latent"].append(np.asarray(updates["anchor"].latent))
        seen["mlp_opacity"].append(jax.tree_util.tree_leaves(updates["decoder"]["opacity"])[0])
        seen["mlp_color"].append(jax.tree_util.tree_leaves(updates["decoder"]["color"])[0])
        seen["appearance"].append(np.asarray(updates["appearance"]))
        seen["features"].append(jax.tree_util.tree_leaves(updates["memory"])[0])
    for group, steps in seen.items():
        init, final = cfg.groups()[group]
        if group == "offsets":  # Scaffold-GS spatial_lr_scale
            init, final = init * EXTENT, final * EXTENT
        schedule = log_linear_schedule(init, final, CFG.train.iterations)
        for count, update in enumerate(steps):
            np.testing.assert_allclose(np.asarray(update), -float(schedule(count)), rtol=1e-4, err_msg=group)
        np.testing.assert_allclose(np.asarray(steps[-1]), -final, rtol=1e-4, err_msg=group)


def test_batch_scaled_is_the_identity_for_one_view_and_gsplats_rule_otherwise():
    from cusgs_jax.training.optim import ADAM_BETAS, batch_scaled

    assert batch_scaled(1, 1e-15) == (1.0, 1e-15, ADAM_BETAS)  # B = 1: exactly today's settings
    scale, eps, (b1, b2) = batch_scaled(4, 1e-15)
    assert scale == 2.0 and eps == 0.5e-15
    assert b1 == pytest.approx(0.9 ** 4) and b2 == pytest.approx(0.999 ** 4)
    # gsplat's first-order 1 − B(1 − β) agrees for small B and stays positive where it does not (B = 10)
    assert abs(b2 - (1 - 4 * 0.001)) < 1e-5
    assert batch_scaled(10, 1e-15)[2][0] > 0 and 1 - 10 * (1 - 0.9) < 1e-12


def test_batch_size_scales_the_learning_rates_by_its_square_root():
    trainable = {"anchor": {"latent": jnp.zeros((3, 2))}}
    grads = {"anchor": {"latent": jnp.ones((3, 2))}}

    def first_update(batch_size):
        opt = make_optimizer(OptimConfig(), trainable, 100, 1.0, batch_size)
        updates, _ = opt.update(grads, opt.init(trainable), trainable)
        return float(updates["anchor"]["latent"][0, 0])

    # Adam's first step moves every entry by ≈ lr (sign of the gradient), so the ratio is √B
    assert first_update(4) / first_update(1) == pytest.approx(2.0, rel=1e-4)


@pytest.mark.parametrize("batch_size", [1, 4])
def test_learning_rates_as_arguments_give_optax_adams_updates_bit_for_bit(batch_size):
    """``make_optimizer``'s update with ``learning_rates`` given (the step's argument) and without (the rates it
    was built with) equals per-group ``optax.adam(log_linear_schedule(...))`` under jit, state and updates,
    over 120 steps of random gradients (past the schedule's end at 100: the clip)."""
    import optax

    from cusgs_jax.training.optim import batch_scaled, group_rates, rate_arguments

    rng = np.random.default_rng(batch_size)
    params = {"anchor": {"offsets": jnp.asarray(rng.normal(size=(5, 3)), jnp.float32),
                         "latent": jnp.asarray(rng.normal(size=(5, 4)), jnp.float32)},
              "decoder": {"opacity": {"w": jnp.asarray(rng.normal(size=(4, 2)), jnp.float32)}},
              "appearance": jnp.zeros((2, 3))}
    cfg = OptimConfig()
    _, eps, (b1, b2) = batch_scaled(batch_size, cfg.eps)
    reference = optax.multi_transform(
        {name: optax.adam(log_linear_schedule(init, final, 100), b1=b1, b2=b2, eps=eps)
         for name, (init, final) in group_rates(cfg, 2.7, batch_size).items()}, param_labels(params))
    tx = make_optimizer(cfg, params, 100, 2.7, batch_size)
    rates = rate_arguments(group_rates(cfg, 2.7, batch_size))
    given = jax.jit(lambda g, s: tx.update(g, s, params, learning_rates=rates))
    built = jax.jit(lambda g, s: tx.update(g, s, params))
    expected = jax.jit(lambda g, s: reference.update(g, s, params))
    states = [tx.init(params), tx.init(params), reference.init(params)]
    assert len({jax.tree_util.tree_structure(s) for s in states}) == 1  # checkpoints keep their layout
    for _ in range(120):
        grads = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape), jnp.float32), params)
        outs = [fn(grads, s) for fn, s in zip((given, built, expected), states)]
        states = [state for _, state in outs]
        for a, b, c in zip(*(jax.tree_util.tree_leaves(out) for out in outs)):
            np.testing.assert_array_equal(a, c)
            np.testing.assert_array_equal(b, c)
