"""Scaffold-GS growing and pruning on masks."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from cusgs_jax.grow_prune import GrowConfig, GrowStats, accumulate_stats, adjust_anchors
from cusgs_jax.scaffold import AnchorParams, Anchors


class _AlwaysKeep:
    """Stands in for np.random.Generator: every random draw is 1 (keep every candidate)."""

    def random(self, shape):
        return np.ones(shape)


def _state(capacity=8, alive=3, n=2):
    centers = np.zeros((capacity, 3), np.float32)
    centers[:alive] = np.arange(alive)[:, None] * np.array([1.0, 0, 0])
    params = AnchorParams(offsets=jnp.zeros((capacity, n, 3)), log_scaling=jnp.zeros((capacity, 6)),
                          latent=jnp.asarray(np.arange(capacity * 4, dtype=np.float32).reshape(capacity, 4)))
    anchors = Anchors(jnp.asarray(centers), jnp.asarray(np.arange(capacity) < alive))
    return params, anchors


def test_accumulate_stats_formula():
    stats = GrowStats.zeros(2, 2)
    grad = jnp.array([[[0.1, 0.0], [0.0, 0.2]], [[1.0, 1.0], [0.0, 0.0]]])
    out = accumulate_stats(stats, jnp.array([True, False]), jnp.array([[0.5, -0.2], [0.9, 0.9]]),
                           jnp.array([[True, False], [False, False]]), grad, 100, 50, jnp.array(True))
    np.testing.assert_allclose(out.grad_accum, [[0.1 * 50, 0], [0, 0]], rtol=1e-6)
    np.testing.assert_allclose(out.grad_count, [[1, 0], [0, 0]])
    np.testing.assert_allclose(out.opacity_accum, [0.5, 0.0])
    np.testing.assert_allclose(out.visits, [1, 0])
    off = accumulate_stats(stats, jnp.array([True, True]), jnp.ones((2, 2)), jnp.ones((2, 2), bool), grad,
                           100, 50, jnp.array(False))
    assert float(jnp.sum(off.visits)) == 0.0


def test_growing_fills_dead_slots_in_unoccupied_cells():
    cfg = GrowConfig(interval=10, levels=1, init_factor=1, hierarchy_factor=4)
    params, anchors = _state()
    offsets = np.zeros((8, 2, 3), np.float32)
    offsets[0, 0] = [0.0, 0.0, 3.0]  # Gaussian of anchor 0 at (0,0,3): an empty cell
    offsets[1, 1] = [1.0, 0.0, 0.0]  # at (2,0,0): occupied by anchor 2 → no new anchor
    params = AnchorParams(jnp.asarray(offsets), params.log_scaling, params.latent)
    stats = GrowStats(grad_accum=jnp.full((8, 2), 0.01) * 10, grad_count=jnp.full((8, 2), 10.0),
                      opacity_accum=jnp.ones(8), visits=jnp.ones(8))
    new_params, new_anchors, new_stats, _, info = adjust_anchors(params, anchors, stats, {}, cfg, 1.0, _AlwaysKeep())
    alive = np.asarray(new_anchors.alive)
    assert info["grown"] == 1 and alive.sum() == 4
    slot = 3
    np.testing.assert_allclose(new_anchors.centers[slot], [0, 0, 3])
    np.testing.assert_allclose(new_params.latent[slot], params.latent[0])  # max over its one parent
    np.testing.assert_allclose(new_params.offsets[slot], 0)
    np.testing.assert_allclose(new_params.log_scaling[slot], 0.0)  # log(cell = 1)
    assert float(jnp.sum(new_stats.grad_count[:3])) == 0.0  # participating Gaussians reset


def test_pruning_removes_seasoned_transparent_anchors():
    cfg = GrowConfig(interval=100, min_opacity=0.005)
    params, anchors = _state()
    stats = GrowStats(grad_accum=jnp.zeros((8, 2)), grad_count=jnp.zeros((8, 2)),
                      opacity_accum=jnp.array([0.1, 10.0, 0.1, 0, 0, 0, 0, 0]),
                      visits=jnp.array([100.0, 100.0, 50.0, 0, 0, 0, 0, 0]))
    _, new_anchors, new_stats, _, info = adjust_anchors(params, anchors, stats, {}, cfg, 1.0, _AlwaysKeep())
    np.testing.assert_array_equal(np.asarray(new_anchors.alive)[:3], [False, True, True])
    assert info["pruned"] == 1
    np.testing.assert_allclose(new_stats.visits[:3], [0, 0, 50])  # seasoned ones reset


def test_capacity_grows_when_full():
    cfg = GrowConfig(interval=10, levels=1, init_factor=1, capacity_growth=1.5)
    params, anchors = _state(capacity=3, alive=3)
    offsets = np.zeros((3, 2, 3), np.float32)
    offsets[:, 0, 2] = [5.0, 6.0, 7.0]
    params = AnchorParams(jnp.asarray(offsets), params.log_scaling, params.latent)
    stats = GrowStats(jnp.full((3, 2), 1.0), jnp.full((3, 2), 10.0), jnp.ones(3), jnp.ones(3))
    opt_state = {"anchor": {"mu": jnp.ones((3, 4))}}
    new_params, new_anchors, _, new_opt, info = adjust_anchors(params, anchors, stats, opt_state, cfg, 1.0,
                                                               _AlwaysKeep())
    assert info["capacity_grew"] == 3 and info["capacity"] >= 6
    assert new_params.latent.shape[0] == info["capacity"] == new_anchors.alive.shape[0]
    assert new_opt["anchor"]["mu"].shape[0] == info["capacity"]
    assert int(np.sum(new_anchors.alive)) == 6
    # the new slots' optimiser moments start at zero
    assert float(jnp.sum(new_opt["anchor"]["mu"][3:])) == 0.0
