"""Orbax checkpoints of the whole training state (training/checkpoint.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.config import Config
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import make_strategies
from cusgs_jax.training.checkpoint import Checkpointer
from cusgs_jax.training.state import TrainState, init_train_state

CFG = Config().replace(train=dict(iterations=10),
                       model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8))


@pytest.fixture(scope="module")
def fresh():
    pts = np.random.default_rng(0).uniform(-1, 1, (300, 3))
    return init_train_state(CFG, pts, 2, 2.0, make_strategies(CFG))


def _perturbed(state, seed):
    """A state whose every float leaf differs from the fresh one (and counters moved)."""
    key = jax.random.PRNGKey(seed)
    leaves, treedef = jax.tree_util.tree_flatten(state)
    keys = jax.random.split(key, len(leaves))
    leaves = [x + jax.random.normal(k, x.shape, x.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
              for x, k in zip(leaves, keys)]
    state = jax.tree_util.tree_unflatten(treedef, leaves)
    return state.replace(step=jnp.int32(7 + seed), skipped=jnp.int32(seed))


def _assert_same(a, b):
    leaves_a, leaves_b = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert len(leaves_a) == len(leaves_b) > 0
    for x, y in zip(leaves_a, leaves_b):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(x, y)


def test_save_restore_round_trip_is_exact(fresh, tmp_path):
    template, _ = fresh
    saved = _perturbed(template, 1)
    ckpt = Checkpointer(tmp_path / "ckpt")
    assert ckpt.latest_step() is None
    ckpt.save(8, saved, {"step": 8, "curve": [{"step": 5, "psnr": 12.5}], "capacity": saved.anchors.capacity})
    assert ckpt.latest_step() == 8 and ckpt.step_bytes() > 0
    assert ckpt.metadata() == {"step": 8, "curve": [{"step": 5, "psnr": 12.5}], "capacity": saved.anchors.capacity}
    restored, meta = ckpt.restore(template)
    ckpt.close()
    assert isinstance(restored, TrainState) and meta["step"] == 8
    _assert_same(restored, saved)
    # a new Checkpointer on the same folder (a resumed process) finds it too
    again = Checkpointer(tmp_path / "ckpt")
    assert again.latest_step() == 8
    _assert_same(again.restore(template)[0], saved)
    again.close()


def test_keeps_the_newest_and_restores_any_kept_step(fresh, tmp_path):
    template, _ = fresh
    ckpt = Checkpointer(tmp_path / "ckpt", max_to_keep=2)
    states = {step: _perturbed(template, step) for step in (1, 2, 3)}
    for step, state in states.items():
        ckpt.save(step, state, {"step": step})
    assert ckpt.latest_step() == 3
    assert sorted(int(p.name) for p in (tmp_path / "ckpt").iterdir() if p.name.isdigit()) == [2, 3]
    _assert_same(ckpt.restore(template, step=2)[0], states[2])
    assert ckpt.metadata(2) == {"step": 2}
    ckpt.close()


def test_half_written_checkpoint_is_ignored(fresh, tmp_path):
    template, _ = fresh
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(4, _perturbed(template, 4), {"step": 4})
    ckpt.close()
    partial = tmp_path / "ckpt" / "9.orbax-checkpoint-tmp-1234"
    partial.mkdir()
    (partial / "junk").write_text("partial")
    resumed = Checkpointer(tmp_path / "ckpt")
    assert resumed.latest_step() == 4
    assert resumed.metadata() == {"step": 4}
    resumed.close()


def test_restore_into_a_grown_capacity(fresh, tmp_path):
    """A run whose capacity grew is restored into a template padded to the saved capacity."""
    template, tx = fresh
    grown = _perturbed(ops.grow_capacity(template, tx, template.anchors.capacity + 17), 5)
    ckpt = Checkpointer(tmp_path / "ckpt")
    ckpt.save(5, grown, {"capacity": grown.anchors.capacity})
    capacity = ckpt.metadata()["capacity"]
    restored, _ = ckpt.restore(ops.grow_capacity(template, tx, capacity))
    ckpt.close()
    assert restored.anchors.capacity == template.anchors.capacity + 17
    _assert_same(restored, grown)
