"""Several processes (one per node) as one JAX job: joining it, and what works across it.

The cluster starts the processes, not cusgs-jax. Under SLURM, one task per node::

    #SBATCH --nodes=2 --ntasks-per-node=1 --gpus-per-node=4
    srun python my_training.py          # every task runs the same script

and in the script, before any other JAX call, :func:`initialize` — with no arguments JAX reads
the coordinator address, process count and process index from SLURM's environment
(``SLURM_JOB_NODELIST``, ``SLURM_NTASKS``, ``SLURM_PROCID``; ``jax.distributed`` cluster
auto-detection). Elsewhere (two processes on one machine, a cloud VM group) pass them:
``initialize("host0:1234", num_processes=2, process_id=i)``. ``jax.devices()`` then lists the
devices of every process; :func:`cusgs_jax.training.parallel.view_mesh` spans them, and the
batched step (:func:`cusgs_jax.training.step.make_batched_step`) shards its B views over all
of them — every process passes the same full batch and state (each loads the whole scene),
:func:`cusgs_jax.training.parallel.place` keeps only its own shards. On CPU, JAX's gloo
collectives carry the gradient sum between processes.

What works across processes today: the training step (tested with two processes on localhost,
``tests/training/test_distributed.py``, equal to one process with two devices). What does not:
the ``cusgs-train`` loop, whose densification, evaluation and checkpoint metadata run on one
host; it refuses to start in a multi-process job (:func:`require_single_process`).
"""

from __future__ import annotations

import jax

from cusgs_jax.config import require


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> None:
    """Join the multi-process job (``jax.distributed.initialize``); with no arguments, from SLURM's environment."""
    jax.distributed.initialize(coordinator_address=coordinator_address, num_processes=num_processes,
                               process_id=process_id)


def local_value(x):
    """The host value of a replicated global array, readable on every process (``x`` itself if addressable)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return jax.device_get(x.addressable_data(0))
    return jax.device_get(x)


def require_single_process() -> None:
    """Refuse a multi-process job in the single-host training loop (one line, exit 2)."""
    require(jax.process_count() == 1, "jax.process_count()", jax.process_count(),
            "cusgs-train runs in one process (its densification, evaluation and checkpoint metadata are host "
            "side); across processes only the training step is supported (cusgs_jax.training.distributed)",
            "use train.batch_size with train.devices=auto to use every device of one node")
