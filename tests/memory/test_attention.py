"""Memory attention: float64 reference, finite differences, masking, numerical safety, blocking."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.memory import attention as att
from cusgs_jax.testing.attention_reference import attend_reference

C, D, S = 6, 10, 9


def make(adapter="affine", seed=0, dtype=np.float32, log_t=None):
    """Random head (non-trivial adapter), queries [4, 5, C], bank [M, D], mask [M]."""
    rng = np.random.default_rng(seed)
    params = att.init_memory_head(jax.random.PRNGKey(seed), C, D, adapter=adapter, rank=3)
    ad = params["adapter"]
    if adapter == "affine":
        ad = {"scale": 1 + 0.3 * rng.normal(size=D), "bias": 0.1 * rng.normal(size=D)}
    else:
        ad = {"u": np.asarray(ad["u"]), "v": 0.3 * rng.normal(size=(D, 3)), "bias": 0.1 * rng.normal(size=D)}
    params = {"key_proj": np.asarray(params["key_proj"]),
              "log_temperature": np.log(0.3) if log_t is None else log_t, "adapter": ad}
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), params)
    queries = jnp.asarray(rng.normal(size=(4, 5, C)), dtype)
    bank = jnp.asarray(rng.normal(size=(S, D)) * rng.uniform(0.5, 3, (S, 1)), dtype)
    valid = jnp.asarray(rng.random(S) < 0.7).at[0].set(True)
    return params, queries, bank, valid


@jax.jit(static_argnames=("block",))
def run(params, queries, bank, valid=None, block=None):
    return att.attend(params, queries, att.precompute_keys(params, bank), bank, valid, block=block)


@jax.jit(static_argnames=("block",))
def grad_sq(params, queries, bank, valid=None, block=None):
    """Gradients of sum(f^2) w.r.t. params, queries and bank."""
    return jax.grad(lambda p, q, b: jnp.sum(run(p, q, b, valid, block) ** 2), argnums=(0, 1, 2))(
        params, queries, bank)


def finite_tree(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


def test_init_shapes_and_identity_adapters():
    key = jax.random.PRNGKey(1)
    aff = att.init_memory_head(key, C, D)
    low = att.init_memory_head(key, C, D, adapter="lowrank", rank=4)
    assert aff["key_proj"].shape == (C, D) and aff["key_proj"].dtype == jnp.float32
    assert np.isclose(float(aff["log_temperature"]), np.log(0.05))
    assert aff["adapter"]["scale"].shape == (D,) and low["adapter"]["u"].shape == (D, 4)
    assert att.num_params(aff) == C * D + 1 + 2 * D
    assert att.num_params(low) == C * D + 1 + 2 * D * 4 + D
    _, queries, bank, valid = make()
    # Both adapters start as the identity, so both heads give the plain attention read-out.
    np.testing.assert_allclose(run(aff, queries, bank, valid), run(low, queries, bank, valid), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError):
        att.init_memory_head(key, C, D, adapter="dense")


@pytest.mark.parametrize("adapter", ["affine", "lowrank"])
@pytest.mark.parametrize("masked", [False, True])
def test_forward_matches_reference(adapter, masked):
    params, queries, bank, valid = make(adapter)
    valid = valid if masked else None
    want = attend_reference(params, queries, bank, valid)
    got = run(params, queries, bank, valid)
    assert got.shape == (4, 5, D) and got.dtype == jnp.float32
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)
    if not masked:
        return
    with jax.enable_x64(True):
        p64, q64, b64, v64 = make(adapter, dtype=np.float64)
        np.testing.assert_allclose(run(p64, q64, b64, v64), attend_reference(p64, q64, b64, v64),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("adapter", ["affine", "lowrank"])
def test_gradients_match_finite_differences(adapter):
    """jax.grad of the float64 path vs central differences of the NumPy reference."""
    with jax.enable_x64(True):
        params, queries, bank, valid = make(adapter, dtype=np.float64)
        queries = queries.at[0, 0].set(jnp.zeros(C).at[2].set(3.0))  # a one-hot query too
        weights = jnp.asarray(np.random.default_rng(5).normal(size=(4, 5, D)))

        def loss(p, q, b):
            return jnp.sum(run(p, q, b, valid) * weights)

        def loss_ref(p, q, b):
            return float(np.sum(attend_reference(p, q, b, valid) * np.asarray(weights)))

        grads = jax.grad(loss, argnums=(0, 1, 2))(params, queries, bank)
        assert finite_tree(grads)
        args = (params, queries, bank)
        rng = np.random.default_rng(6)
        h = 1e-6
        for argnum in range(3):
            leaves, treedef = jax.tree_util.tree_flatten(args[argnum])
            gleaves = jax.tree_util.tree_leaves(grads[argnum])
            for i, (leaf, g) in enumerate(zip(leaves, gleaves)):
                v = rng.normal(size=np.shape(leaf))
                def shifted(t, i=i, v=v, leaves=leaves, treedef=treedef, argnum=argnum):
                    new = list(leaves)
                    new[i] = np.asarray(leaves[i]) + t * v
                    a = list(args)
                    a[argnum] = jax.tree_util.tree_unflatten(treedef, new)
                    return loss_ref(*a)
                fd = (shifted(h) - shifted(-h)) / (2 * h)
                np.testing.assert_allclose(float(jnp.sum(g * v)), fd, rtol=1e-6, atol=1e-8,
                                           err_msg=f"arg {argnum} leaf {i}")


def test_softmax_shift_invariance():
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        logits = jnp.asarray(rng.normal(size=(3, 7)) * 4)
        valid = jnp.asarray(rng.random((3, 7)) < 0.6).at[:, 0].set(True)
        base = att.masked_softmax(logits, valid)
        for shift in (-1e3, 17.0, 1e3):
            np.testing.assert_allclose(att.masked_softmax(logits + shift, valid), base, rtol=1e-10, atol=1e-14)
        # ... so the gradient along the all-ones direction vanishes.
        w = jnp.asarray(rng.normal(size=(3, 7)))
        g = jax.grad(lambda l: jnp.sum(att.masked_softmax(l, valid) * w))(logits)
        np.testing.assert_allclose(jnp.sum(g, axis=-1), 0.0, atol=1e-12)
    shifted = att.masked_softmax(jnp.asarray(logits, jnp.float32) + 50.0, valid)
    np.testing.assert_allclose(shifted, np.asarray(base), rtol=1e-4, atol=1e-6)


def test_masked_entries_get_exactly_zero_weight():
    params, queries, bank, valid = make()
    w = att.attention_weights(params, queries, att.precompute_keys(params, bank), valid)
    assert np.all(np.asarray(w)[..., ~np.asarray(valid)] == 0.0)
    np.testing.assert_allclose(jnp.sum(w, -1), 1.0, rtol=1e-6)
    # Masked rows of the bank cannot influence the output, even when huge.
    wild = jnp.where(valid[:, None], bank, 1e30)
    np.testing.assert_allclose(run(params, queries, wild, valid), run(params, queries, bank, valid), rtol=1e-6)
    gbank = jax.grad(lambda b: jnp.sum(run(params, queries, b, valid)))(wild)
    assert np.all(np.asarray(gbank)[~np.asarray(valid)] == 0.0) and finite_tree(gbank)


@pytest.mark.parametrize("block", [None, 4])
def test_all_masked_returns_zeros(block):
    params, queries, bank, _ = make()
    none = jnp.zeros(S, bool)
    out = run(params, queries, bank, none, block)
    assert np.all(np.asarray(out) == 0.0)
    assert finite_tree(grad_sq(params, queries, bank, none, block))
    w = att.masked_softmax(jnp.array([[1e30, -1e30]]), jnp.zeros((1, 2), bool))
    assert np.all(np.asarray(w) == 0.0)


def test_extreme_logits():
    logits = jnp.array([[1e30, -1e30, 0.0, 1e30], [-1e30, -1e30, -3e38, 3e38]], jnp.float32)
    w = att.masked_softmax(logits)
    np.testing.assert_allclose(w, [[0.5, 0, 0, 0.5], [0, 0, 0, 1]])
    g = jax.grad(lambda l: jnp.sum(att.masked_softmax(l) * jnp.arange(4.0)))(logits)
    assert finite_tree(g)


@pytest.mark.parametrize("log_t", [np.log(1e-6), np.log(1e6), -1e3, 1e3, 0.0])
@pytest.mark.parametrize("query_scale", [0.0, 1e-30, 1.0, 1e30])
def test_extreme_temperatures_and_queries_are_finite(log_t, query_scale):
    params, queries, bank, valid = make(log_t=log_t)
    queries = queries * query_scale
    queries = queries.at[0, 0].set(0.0)  # always one exactly-zero query
    out = run(params, queries, bank, valid)
    assert finite_tree(out)
    assert finite_tree(grad_sq(params, queries, bank, valid))
    if query_scale == 0.0:  # zero queries: uniform attention over the valid entries
        v = np.asarray(valid)
        mean = np.asarray(bank)[v].mean(0) * np.asarray(params["adapter"]["scale"]) + np.asarray(
            params["adapter"]["bias"])
        np.testing.assert_allclose(out, np.broadcast_to(mean, out.shape), rtol=1e-5, atol=1e-5)
    if log_t == np.log(1e6):  # a very hot softmax is uniform too
        np.testing.assert_allclose(out, out[0, 0] + 0 * out, rtol=1e-4, atol=1e-4)


def test_safe_normalize():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 4))
    for scale in (1e-30, 1.0, 1e30):
        np.testing.assert_allclose(att.safe_normalize(jnp.asarray(x * scale, jnp.float32)),
                                   x / np.linalg.norm(x, axis=-1, keepdims=True), rtol=1e-6, atol=1e-7)
    assert np.all(np.asarray(att.safe_normalize(jnp.zeros((2, 3)))) == 0.0)
    jacobian = jax.jit(jax.jacobian(att.safe_normalize))
    np.testing.assert_array_equal(jacobian(jnp.zeros(4)), np.eye(4))
    with jax.enable_x64(True):
        for v in (jnp.array([0.0, 3.0, 0.0, 0.0]), jnp.asarray(rng.normal(size=4))):  # one-hot and generic
            n = np.linalg.norm(v)
            want = (np.eye(4) - np.outer(v, v) / n**2) / n
            np.testing.assert_allclose(jacobian(v), want, rtol=1e-12, atol=1e-14)


def test_blocked_equals_unblocked():
    params, queries, bank, valid = make("lowrank")
    full = run(params, queries, bank, valid)
    for block in (1, 7):  # 20 queries: one per block, a ragged last block
        np.testing.assert_allclose(run(params, queries, bank, valid, block), full, rtol=1e-6, atol=1e-6)
    gfull, gblk = grad_sq(params, queries, bank, valid), grad_sq(params, queries, bank, valid, 7)
    for a, b in zip(jax.tree_util.tree_leaves(gfull), jax.tree_util.tree_leaves(gblk)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(a))))
    single = run(params, queries[0, 0], bank, valid, 7)  # a lone [c] query
    np.testing.assert_allclose(single, full[0, 0], rtol=1e-6, atol=1e-6)


def test_jit_and_vmap():
    params, queries, bank, valid = make()
    keys = att.precompute_keys(params, bank)
    eager = att.attend(params, queries, keys, bank, valid)
    jitted = jax.jit(att.attend, static_argnames=("block",))
    np.testing.assert_allclose(jitted(params, queries, keys, bank, valid), eager, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(jitted(params, queries, keys, bank, valid, block=6), eager, rtol=1e-6, atol=1e-6)
    over_queries = jax.vmap(lambda q: att.attend(params, q, keys, bank, valid))(queries)
    np.testing.assert_allclose(over_queries, eager, rtol=1e-6, atol=1e-6)
    # Two heads stacked: vmap over parameters (and their keys).
    other, _, _, _ = make(seed=1)
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), params, other)
    both = jax.jit(jax.vmap(lambda p: run(p, queries, bank, valid)))(stacked)
    np.testing.assert_allclose(both[0], eager, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(both[1], run(other, queries, bank, valid), rtol=1e-6, atol=1e-6)


def test_bad_shapes():
    params, queries, bank, valid = make()
    keys = att.precompute_keys(params, bank)
    with pytest.raises(ValueError):
        att.attend(params, queries, keys, bank[:-1])
    with pytest.raises(ValueError):
        att.attend(params, queries, keys, bank, valid[:-1])
    with pytest.raises(ValueError):
        att.attend(params, queries, keys, bank, block=0)
