"""app/compiles.py: every XLA compilation is recorded with its function, seconds and whether it was loaded."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.app.ahead import Program
from cusgs_jax.app.compiles import CompileLog


class _Placed:
    """What the batched step looks like to the compile log: a callable holding its jitted part as ``jitted``."""

    def __init__(self, jitted):
        self.jitted = jitted


def test_each_new_program_is_recorded_once_by_name_and_a_cached_call_is_not():
    def my_distinct_function(x):
        return jnp.sin(x) * 3.0 + 1.0

    fn = jax.jit(my_distinct_function)
    with CompileLog() as log:
        fn(jnp.ones(7)).block_until_ready()
        fn(jnp.ones(7)).block_until_ready()  # jit's in-memory cache: nothing compiled
        fn(jnp.ones(9)).block_until_ready()  # a new shape: a new program
    assert log.count("jit(my_distinct_function)") == 2 == log.count(fn)  # by name, or by the function itself
    assert log.count(Program(fn)) == 2 == log.count(_Placed(fn))  # through what wraps it (app/ahead.py, the batched step)
    records = [r for r in log.records if r["function"] == "jit(my_distinct_function)"]
    assert all(r["seconds"] >= r["backend_seconds"] > 0 for r in records)
    assert log.seconds >= log.backend_seconds >= sum(r["backend_seconds"] for r in records) - 1e-3
    fn(jnp.ones(11)).block_until_ready()  # after the block: not recorded
    assert log.count("jit(my_distinct_function)") == 2


def test_summary_ranks_functions_and_folds_the_rest():
    log = CompileLog()
    for i in range(5):
        log.records.append(dict(function=f"jit(f{i})", seconds=float(i + 1), backend_seconds=float(i), cached=i == 0))
    log.seconds = 15.0
    summary = log.summary(top=2)
    assert summary["count"] == 5 and summary["from_cache"] == 1 and summary["compiled"] == 4
    assert list(summary["functions"]) == ["jit(f4)", "jit(f3)", "other"]
    assert summary["functions"]["other"] == dict(count=3, seconds=6.0)
    assert np.isclose(summary["seconds"], 15.0)
