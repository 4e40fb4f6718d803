"""A process of the two-process test (tests/training/test_distributed.py): the batched step over every process.

``python -m cusgs_jax.testing.distributed_step PORT PROCESS_ID OUT.json``: joins a 2-process job on
localhost, runs :func:`run_steps` (B = 2 views sharded over the 2 processes' devices) and writes the
losses and the final parameters' sums (process 0 only). The test runs the same steps in one process.
"""

from __future__ import annotations

import json
import sys

import jax
import numpy as np

from cusgs_jax.config import Config
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.testing.scenes import sfm_points
from cusgs_jax.training.distributed import initialize, local_value
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def run_steps(steps: int = 2) -> dict:
    """``steps`` B = 2 steps of the tiny test scene on the global view mesh: {"losses", "param_sums"}."""
    width, height = 32, 24
    cfg = Config().replace(train=dict(iterations=50, batch_size=2, devices="2"),
                           model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8),
                           grow=dict(stats_start=0, start=5, stop=50, interval=5))
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies)
    step = make_train_step(cfg, tx, strategies)
    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], np.float32)
    losses = []
    for i in range(steps):
        rng = np.random.default_rng(i)
        images = rng.uniform(0, 1, (2, height, width, 3)).astype(np.float32)
        viewmats = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
        viewmats[:, :3, 3] = rng.normal(0, 0.05, (2, 3))
        batch = dict(image=images, camera=Camera(np.stack([K, K]), viewmats, width, height),
                     index=np.arange(2, dtype=np.int32))
        state, metrics = step(state, batch)
        losses.append(float(local_value(metrics["loss"])))
    sums = [float(np.sum(np.asarray(local_value(x), np.float64))) for x in jax.tree_util.tree_leaves(state.trainable)]
    return dict(losses=losses, param_sums=sums, devices=int(step.mesh.size), processes=jax.process_count())


def main() -> None:
    port, process_id, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    initialize(f"localhost:{port}", num_processes=2, process_id=process_id)
    result = run_steps()
    if process_id == 0:
        with open(out, "w") as f:
            json.dump(result, f)


if __name__ == "__main__":
    main()
