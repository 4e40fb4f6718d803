"""Check that train.batch_size=1 trains bit for bit as the step of an earlier commit did.

    python experiments/b1_bit_identity.py [REV]      # REV: a commit before the batched step (default 971d7e1)

Loads ``src/cusgs_jax/training/step.py`` as it was at REV (``git show``) beside today's, runs 5
steps (with growing statistics and pruning statistics) of each from the same state on the same
views, and prints whether every leaf of the final state and metrics is identical.
"""

from __future__ import annotations

import importlib.util
import json
import pathlib
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import Config
from cusgs_jax.densify.base import make_strategies
from cusgs_jax.testing.scenes import sfm_points
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def _old_step_module(rev: str):
    source = subprocess.run(["git", "show", f"{rev}:src/cusgs_jax/training/step.py"], capture_output=True, text=True,
                            check=True, cwd=pathlib.Path(__file__).parent).stdout
    path = pathlib.Path(tempfile.mkdtemp()) / "old_step.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("old_step", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    rev = sys.argv[1] if len(sys.argv) > 1 else "971d7e1"
    width, height = 32, 24
    K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    cfg = Config().replace(train=dict(iterations=50),
                           model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
                           grow=dict(stats_start=0, start=5, stop=50, interval=5))

    def batch(seed):
        rng = np.random.default_rng(seed)
        view = np.eye(4, dtype=np.float32)
        view[:3, 3] = rng.normal(0, 0.05, 3)
        return dict(image=jnp.asarray(rng.uniform(0, 1, (height, width, 3)).astype(np.float32)),
                    camera=Camera(K, jnp.asarray(view), width, height), index=jnp.int32(seed % 2))

    finals = []
    for make in (_old_step_module(rev).make_train_step, make_train_step):
        strategies = make_strategies(cfg)
        state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies)
        step = make(cfg, tx, strategies)
        for i in range(5):
            state, metrics = step(state, batch(i))
        finals.append(jax.tree_util.tree_leaves(jax.device_get((state, metrics))))
    identical = len(finals[0]) == len(finals[1]) and all(
        np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(*finals))
    print(json.dumps(dict(rev=rev, leaves=len(finals[1]), bit_identical=bool(identical))))


if __name__ == "__main__":
    main()
