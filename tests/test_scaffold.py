"""Anchor initialisation, voxelisation and capacity growth."""

from __future__ import annotations

import numpy as np

from cusgs_jax.scaffold import grow_capacity, init_anchors, nearest_neighbour_sq_dist, voxelize


def test_voxelize_deduplicates_cells():
    pts = np.array([[0.01, 0.02, 0.0], [0.04, -0.04, 0.02], [0.26, 0.0, 0.0], [0.24, 0.01, -0.01]])
    centers = voxelize(pts, 0.1)
    np.testing.assert_allclose(centers, [[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0]], atol=1e-6)


def test_nearest_neighbour_distance_closed_form():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]])
    d = nearest_neighbour_sq_dist(pts, k=1)
    np.testing.assert_allclose(d, [1.0, 1.0, 4.0, 16.0])


def test_init_anchors_capacity_and_alive_mask():
    rng = np.random.default_rng(0)
    params, anchors = init_anchors(rng.uniform(0, 1, (500, 3)), 0.2, n_offsets=5, latent_dim=8, capacity_factor=2.0)
    num = int(anchors.alive.sum())
    assert anchors.capacity == int(np.ceil(2.0 * num))
    assert params.offsets.shape == (anchors.capacity, 5, 3)
    assert params.latent.shape == (anchors.capacity, 8)
    assert np.all(np.asarray(anchors.alive[:num])) and not np.any(np.asarray(anchors.alive[num:]))
    assert np.all(np.asarray(params.offsets) == 0)
    assert np.isfinite(np.asarray(params.log_scaling)).all()


def test_grow_capacity_pads_only_capacity_shaped_leaves():
    params, anchors = init_anchors(np.random.default_rng(1).uniform(0, 1, (50, 3)), 0.3)
    tree = dict(p=params, a=anchors, other=np.zeros((7, 2)))
    grown = grow_capacity(tree, anchors.capacity, anchors.capacity + 10)
    assert grown["p"].latent.shape[0] == anchors.capacity + 10
    assert grown["a"].alive.shape[0] == anchors.capacity + 10
    assert not np.asarray(grown["a"].alive[anchors.capacity:]).any()
    assert grown["other"].shape == (7, 2)
