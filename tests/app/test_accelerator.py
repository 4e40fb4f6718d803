"""app/accelerator.py: the memory share a sweep job takes of a shared accelerator."""

from __future__ import annotations

from cusgs_jax.app.accelerator import MEM_FRACTION, PREALLOCATE, accelerator_record, sweep_memory_env


def test_jobs_side_by_side_split_the_memory_and_one_at_a_time_take_the_default():
    assert sweep_memory_env(2, {}) == {MEM_FRACTION: "0.450"}
    assert sweep_memory_env(4, {}) == {MEM_FRACTION: "0.225"}
    assert sweep_memory_env(1, {}) == {} and sweep_memory_env(None, {}) == {}
    assert sweep_memory_env(-1, {}) == {PREALLOCATE: "false"}  # as many jobs as cores: allocate on demand


def test_the_users_own_memory_settings_win():
    assert sweep_memory_env(2, {MEM_FRACTION: "0.3"}) == {}
    assert sweep_memory_env(2, {PREALLOCATE: "false"}) == {}


def test_the_record_names_the_backend_and_what_the_job_ran_with():
    record = accelerator_record({MEM_FRACTION: "0.450"})
    assert record["backend"] in ("cpu", "gpu", "cuda", "rocm", "tpu") and record["devices"]
    assert record["memory_fraction"] == "0.450" and record["preallocate"] is None
