"""Anchors: voxelisation, initialisation, the per-anchor row operations, refill and compaction."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.model.anchors import (AnchorParams, AnchorState, PerAnchor, capacity_rung, compact,
                                     init_anchors, map_rows,
                                     nearest_neighbour_sq_dist, pad_rows, parameter_counts, place_anchors,
                                     take_rows, voxelize, zero_rows)


def _distinct_anchors(capacity=10, n=3, f=4, q=5, alive=None) -> AnchorState:
    """Anchors whose every number is distinct, so a moved or lost row is noticed."""
    rng = np.random.default_rng(7)
    alive = np.ones(capacity, bool) if alive is None else np.asarray(alive, bool)
    params = AnchorParams(offsets=jnp.asarray(rng.normal(size=(capacity, n, 3)), jnp.float32),
                          log_scaling=jnp.asarray(rng.normal(size=(capacity, 6)), jnp.float32),
                          latent=jnp.asarray(rng.normal(size=(capacity, f)), jnp.float32),
                          query_table=jnp.asarray(rng.normal(size=(capacity, n, q)), jnp.float32))
    return AnchorState(jnp.asarray(rng.normal(size=(capacity, 3)), jnp.float32), jnp.asarray(alive), params)


def _leaves(anchors: AnchorState) -> dict[str, np.ndarray]:
    p = anchors.params
    return dict(centers=np.asarray(anchors.centers), alive=np.asarray(anchors.alive),
                offsets=np.asarray(p.offsets), log_scaling=np.asarray(p.log_scaling),
                latent=np.asarray(p.latent), query_table=np.asarray(p.query_table))


def test_voxelize_deduplicates_cells():
    pts = np.array([[0.01, 0.02, 0.0], [0.04, -0.04, 0.02], [0.26, 0.0, 0.0], [0.24, 0.01, -0.01]])
    centers = voxelize(pts, 0.1)
    np.testing.assert_allclose(centers, [[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0]], atol=1e-6)


def test_nearest_neighbour_distance_closed_form():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]])
    d = nearest_neighbour_sq_dist(pts, k=1)
    np.testing.assert_allclose(d, [1.0, 1.0, 4.0, 16.0])


def test_init_anchors_capacity_and_alive_mask():
    points = np.random.default_rng(0).uniform(0, 1, (500, 3))
    anchors = init_anchors(points, 0.2, n_offsets=5, latent_dim=8, capacity_factor=2.0)
    params = anchors.params
    num = int(anchors.alive.sum())
    assert anchors.capacity == int(np.ceil(2.0 * num))
    laddered = init_anchors(points, 0.2, n_offsets=5, latent_dim=8, capacity_factor=2.0, ladder=True)
    assert laddered.capacity == capacity_rung(int(np.ceil(2.0 * num))) >= 2 * num
    # with the ladder, 100 and 110 anchors (one per lattice cell) stand on one rung: one capacity, one program
    lattice = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sizes = {init_anchors(lattice[:n], 1.0, n_offsets=2, latent_dim=3, ladder=ladder).capacity
             for n in (100, 110) for ladder in (True,)}
    assert sizes == {256}
    assert init_anchors(lattice[:110], 1.0, n_offsets=2, latent_dim=3).capacity == 220  # off the ladder
    assert params.offsets.shape == (anchors.capacity, 5, 3)
    assert params.latent.shape == (anchors.capacity, 8)
    assert np.all(np.asarray(anchors.alive[:num])) and not np.any(np.asarray(anchors.alive[num:]))
    assert np.all(np.asarray(params.offsets) == 0)
    assert np.isfinite(np.asarray(params.log_scaling)).all()
    assert params.query_table is None  # no table unless a query size is asked for
    table = init_anchors(points, 0.2, n_offsets=5, latent_dim=8, query_dim=7,
                         key=jax.random.PRNGKey(1)).params.query_table
    assert table.shape == (anchors.capacity, 5, 7) and 0.05 < float(jnp.std(table)) < 0.2


def test_grow_capacity_pads_only_capacity_shaped_leaves():
    """``pad_rows`` grows the leaves of :class:`PerAnchor` nodes only — never an array that merely
    happens to have the capacity as its leading axis."""
    anchors = init_anchors(np.random.default_rng(1).uniform(0, 1, (50, 3)), 0.3)
    cap = anchors.capacity
    tree = dict(p=anchors.params, a=anchors, other=np.zeros((7, 2)), lookalike=jnp.ones((cap, 2)))
    grown = pad_rows(tree, cap + 10)
    assert grown["p"].latent.shape[0] == cap + 10
    assert grown["a"].alive.shape[0] == cap + 10
    assert not np.asarray(grown["a"].alive[cap:]).any()
    assert grown["other"].shape == (7, 2)
    assert grown["lookalike"].shape == (cap, 2)
    # the old rows are kept, the new ones are zero
    np.testing.assert_array_equal(grown["a"].params.log_scaling[:cap], anchors.params.log_scaling)
    np.testing.assert_array_equal(grown["a"].centers[:cap], anchors.centers)
    assert not np.any(np.asarray(grown["a"].params.log_scaling[cap:]))


def test_map_rows_sees_every_per_anchor_node_and_nothing_else():
    seen = []
    anchors = _distinct_anchors(capacity=6)
    tree = {"anchors": anchors, "net": {"w": jnp.ones((6, 6))}, "count": jnp.int32(3), "none": None}
    out = map_rows(lambda x: seen.append(x.shape) or x[:2], tree)
    # 6 per-anchor leaves: centres, alive, offsets, log_scaling, latent, query_table
    assert len(seen) == 6 and all(s[0] == 6 for s in seen)
    assert out["anchors"].capacity == 2 and out["anchors"].params.query_table.shape == (2, 3, 5)
    assert out["net"]["w"].shape == (6, 6) and int(out["count"]) == 3 and out["none"] is None
    assert isinstance(out["anchors"], PerAnchor)


def test_take_and_zero_rows():
    anchors = _distinct_anchors(capacity=8)
    before = _leaves(anchors)
    index = np.array([5, 0, 5, 7])
    taken = _leaves(take_rows(anchors, index))
    for name, x in before.items():
        np.testing.assert_array_equal(taken[name], x[index], err_msg=name)
    rows = np.zeros(8, bool)
    rows[[1, 6]] = True
    zeroed = _leaves(zero_rows(anchors, rows))
    for name, x in before.items():
        assert not np.any(zeroed[name][rows]), name
        np.testing.assert_array_equal(zeroed[name][~rows], x[~rows], err_msg=name)


def test_place_anchors_refills_dead_slots_from_scratch():
    alive = np.array([True, False, True, False, False, True])
    anchors = _distinct_anchors(capacity=6, alive=alive)
    before = _leaves(anchors)
    slots = np.array([3, 1])
    centers = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.float32)
    latent = np.arange(8, dtype=np.float32).reshape(2, 4)
    log_scale = np.array([-1.5, -2.5], np.float32)
    after = _leaves(place_anchors(anchors, slots, centers, latent, log_scale, jax.random.PRNGKey(4)))
    np.testing.assert_array_equal(after["alive"], alive | np.isin(np.arange(6), slots))
    np.testing.assert_array_equal(after["centers"][slots], centers)
    np.testing.assert_array_equal(after["latent"][slots], latent)
    np.testing.assert_array_equal(after["offsets"][slots], 0.0)
    np.testing.assert_array_equal(after["log_scaling"][slots], np.repeat(log_scale[:, None], 6, axis=1))
    assert np.all(after["query_table"][slots] != before["query_table"][slots])  # fresh queries
    untouched = ~np.isin(np.arange(6), slots)
    for name, x in before.items():
        np.testing.assert_array_equal(after[name][untouched], x[untouched], err_msg=name)


def test_compact_keeps_alive_rows_in_order_and_drops_dead_ones():
    alive = np.zeros(20, bool)
    alive[[2, 3, 7, 11, 12, 19]] = True
    anchors = _distinct_anchors(capacity=20, alive=alive)
    before = _leaves(anchors)
    keep = np.flatnonzero(alive)
    for multiple, capacity in ((4, 8), (3, 6), (64, 64)):
        compacted = compact(anchors, multiple=multiple)
        after = _leaves(compacted)
        assert compacted.capacity == capacity
        np.testing.assert_array_equal(after["alive"], np.arange(capacity) < len(keep))
        for name, x in before.items():
            assert after[name].shape == (capacity,) + x.shape[1:], name
            if name != "alive":  # alive rows in slot order, every per-anchor array alike
                np.testing.assert_array_equal(after[name][:len(keep)], x[keep], err_msg=name)
        # a dead row's numbers are gone (the padding is dead, whatever it holds)
        dead_latents = before["latent"][~alive]
        assert not any(np.any(np.all(after["latent"][:len(keep)] == z, axis=-1)) for z in dead_latents)
        assert parameter_counts(compacted) == parameter_counts(anchors)


def test_the_capacity_ladder_has_four_rungs_per_doubling():
    caps = [capacity_rung(n) for n in range(1, 40_000)]
    assert all(c >= n and c % 64 == 0 for n, c in zip(range(1, 40_000), caps))
    # at most 25 % padding once the quarter octave exceeds the multiple of 64
    assert all(c <= 1.25 * n for n, c in zip(range(1, 40_000), caps) if n >= 256)
    # a model growing from 5k to 13k anchors (the default demo run) sees 7 shapes, not one per 64 anchors (125)
    assert len({capacity_rung(n) for n in range(5_000, 13_001)}) == 7
    assert [capacity_rung(n) for n in (6, 64, 65, 5202, 8252, 9790, 13044)] == [
        64, 64, 128, 6144, 10240, 10240, 14336]


def test_parameter_counts_only_alive_anchors():
    alive = np.array([True, False, True, True])
    counts = parameter_counts(_distinct_anchors(capacity=4, n=3, f=4, q=5, alive=alive))
    assert counts == {"anchors": 3 * (3 * 3 + 6 + 4 + 3), "query_table": 3 * 3 * 5}
    plain = init_anchors(np.random.default_rng(2).uniform(0, 1, (40, 3)), 0.5, n_offsets=2, latent_dim=3)
    alive_count = int(np.sum(np.asarray(plain.alive)))
    assert parameter_counts(plain) == {"anchors": alive_count * (6 + 6 + 3 + 3), "query_table": 0}


def test_points_at_one_location_are_refused_naming_the_points_not_a_setting():
    from cusgs_jax.errors import UserError
    from cusgs_jax.model.anchors import auto_voxel_size

    with pytest.raises(UserError, match="lie at 1 distinct location.*points3D.*model.voxel_size"):
        auto_voxel_size(np.ones((50, 3)))
