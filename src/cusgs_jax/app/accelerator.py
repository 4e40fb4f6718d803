"""Sharing one accelerator between the jobs of a sweep (docs/scaling.md#one-gpu-several-jobs).

Each JAX process preallocates 75 % of a GPU's memory when its backend starts (JAX docs, "GPU memory
allocation"), so the second job of Hydra's joblib launcher (several jobs at once on one machine)
fails to allocate. A job launched by a sweep with ``n_jobs`` jobs side by side therefore takes
``XLA_PYTHON_CLIENT_MEM_FRACTION`` = 0.9 / n_jobs (what is left covers each process's CUDA context)
before its backend starts — unless the user set that variable or ``XLA_PYTHON_CLIENT_PREALLOCATE``
themselves. On a CPU the variables are read by nothing and change nothing.
"""

from __future__ import annotations

import os

MEM_FRACTION = "XLA_PYTHON_CLIENT_MEM_FRACTION"
PREALLOCATE = "XLA_PYTHON_CLIENT_PREALLOCATE"
SHARED_SHARE = 0.9  # of the device's memory, split between the jobs that run at once


def sweep_memory_env(parallel_jobs: int | None, environ=os.environ) -> dict[str, str]:
    """The environment variables a sweep job sets before JAX starts: {} when nothing needs setting.

    Args:
      parallel_jobs: how many jobs run at once on this machine (the joblib launcher's ``n_jobs``;
        -1 or another value below 1: as many as cores, so preallocation is turned off), or None
        (one job at a time: nothing to share).
      environ: the job's environment (a variable the user set there wins).
    """
    if parallel_jobs is None or parallel_jobs == 1 or MEM_FRACTION in environ or PREALLOCATE in environ:
        return {}
    if parallel_jobs < 1:
        return {PREALLOCATE: "false"}
    return {MEM_FRACTION: f"{SHARED_SHARE / parallel_jobs:.3f}"}


def accelerator_record(environ=os.environ) -> dict:
    """``eval.json``'s ``accelerator``: the backend, its devices and the memory settings the job ran with."""
    import jax

    return dict(backend=jax.default_backend(), devices=[str(d) for d in jax.local_devices()],
                memory_fraction=environ.get(MEM_FRACTION), preallocate=environ.get(PREALLOCATE))
