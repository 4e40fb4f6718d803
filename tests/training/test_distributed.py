"""Two processes on localhost as one JAX job (training/distributed.py): the batched step spans them."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from cusgs_jax.errors import ConfigError
from cusgs_jax.testing.distributed_step import run_steps
from cusgs_jax.training import distributed


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # 31 s on 2 cores: kept out of the default run; .ci/run's -m slow pass runs it
def test_the_batched_step_over_two_processes_equals_one_process_with_two_devices(tmp_path):
    """Each process has 1 CPU device; the 2-view step is sharded over both (gloo carries the psum).

    Same losses and parameters as this process's two virtual devices, to float32 reduction order.
    """
    port, out = _free_port(), tmp_path / "result.json"
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1", JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-m", "cusgs_jax.testing.distributed_step", str(port), str(i), str(out)],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(2)]
    try:
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(logs)[-3000:]
    two_processes = json.loads(out.read_text())
    assert two_processes["processes"] == 2 and two_processes["devices"] == 2
    one_process = run_steps()
    assert one_process["processes"] == 1 and one_process["devices"] == 2 == jax.device_count()
    np.testing.assert_allclose(two_processes["losses"], one_process["losses"], rtol=1e-5)
    np.testing.assert_allclose(two_processes["param_sums"], one_process["param_sums"], rtol=1e-4, atol=1e-4)


def test_the_training_loop_refuses_several_processes(monkeypatch):
    distributed.require_single_process()  # one process: fine
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    with pytest.raises(ConfigError, match="cusgs-train runs in one process"):
        distributed.require_single_process()
