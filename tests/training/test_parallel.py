"""Views over devices (training/parallel.py): how many devices, the mesh, placement."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.errors import ConfigError
from cusgs_jax.training import parallel


@pytest.mark.parametrize("batch, available, expected", [(1, 8, 1), (2, 1, 1), (2, 2, 2), (4, 2, 2), (6, 4, 3),
                                                        (3, 2, 1), (8, 8, 8)])
def test_auto_takes_the_most_devices_that_divide_the_batch(batch, available, expected):
    assert parallel.resolve_devices(batch, "auto", available) == expected


def test_a_device_count_that_is_not_there_or_does_not_divide_is_refused():
    assert parallel.resolve_devices(4, "2", 2) == 2
    with pytest.raises(ConfigError, match=r"train.devices='4': only 2 device\(s\) are present"):
        parallel.resolve_devices(4, "4", 2)
    with pytest.raises(ConfigError, match="must divide train.batch_size=3"):
        parallel.resolve_devices(3, 2, 2)


def test_view_mesh_is_none_for_one_view_and_spans_the_devices_otherwise():
    assert parallel.view_mesh(Config()) is None
    mesh = parallel.view_mesh(Config().replace(train=dict(batch_size=2)))
    assert mesh.axis_names == (parallel.AXIS,) and mesh.size == min(2, jax.device_count())


def test_place_splits_views_replicates_state_and_keeps_placed_arrays():
    from jax.sharding import Mesh

    # two CPU devices whatever the default backend (tests/conftest.py makes them)
    mesh = Mesh(np.asarray(jax.devices("cpu")[:2]), (parallel.AXIS,))
    state = {"w": jnp.arange(6.0).reshape(2, 3)}
    batch = {"image": np.arange(24.0).reshape(2, 3, 4), "banks": {"m": np.ones((5, 2))}}
    placed_state, placed_batch = parallel.place_step_inputs(mesh, state, batch)
    assert placed_state["w"].sharding.is_fully_replicated
    shards = placed_batch["image"].addressable_shards
    assert len(shards) == 2 and {s.data.shape for s in shards} == {(1, 3, 4)}  # one view per device
    assert placed_batch["banks"]["m"].sharding.is_fully_replicated
    np.testing.assert_array_equal(np.asarray(placed_batch["image"]), batch["image"])
    again, _ = parallel.place_step_inputs(mesh, placed_state, batch)
    assert again["w"] is placed_state["w"]  # already placed: no copy, no new sharding
