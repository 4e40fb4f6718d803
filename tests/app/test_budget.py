"""app/budget.py: a run's wall time charged to one stage at a time, compilation moved into its own entry."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import pytest

from cusgs_jax.app.budget import STAGES, TimeBudget
from cusgs_jax.app.compiles import CompileLog


def test_stages_add_up_to_the_total_and_nested_stages_charge_the_inner_one():
    budget = TimeBudget(CompileLog())
    block = time.perf_counter()
    with budget.stage("load"):
        time.sleep(0.05)
        with budget.stage("psc"):
            time.sleep(0.1)
        time.sleep(0.02)
    block = time.perf_counter() - block
    time.sleep(0.03)  # outside every stage: "other"
    table = budget.as_dict()
    assert set(table) == set(STAGES) | {"compile_wait", "compile", "other", "total"}
    # lower bounds only: a loaded machine oversleeps, never undersleeps
    assert table["load"] >= 0.07 and table["psc"] >= 0.1 and table["other"] >= 0.03
    assert table["load"] == pytest.approx(block - table["psc"], abs=0.005)  # the inner stage's time is not the outer's
    parts = sum(v for k, v in table.items() if k not in ("total", "compile"))
    assert parts == pytest.approx(table["total"], abs=0.005)


def test_compile_seconds_leave_the_stage_they_happened_in():
    with CompileLog() as log:
        budget = TimeBudget(log, start=time.perf_counter() - 0.2)  # 0.2 s of start-up before it
        with budget.stage("evaluation"):
            jax.jit(lambda x: jnp.cos(x) + 0.5 * x)(jnp.ones(13)).block_until_ready()
        table = budget.as_dict()
    assert table["startup"] >= 0.2 and table["compile_wait"] > 0
    assert table["compile"] == pytest.approx(log.seconds, abs=1e-3)  # compiled on this thread: all of it waited
    assert table["compile_wait"] == pytest.approx(log.foreground_seconds, abs=1e-3) == pytest.approx(log.seconds)
    assert sum(v for k, v in table.items() if k not in ("total", "compile")) == pytest.approx(table["total"], abs=0.005)
    assert budget.line().startswith(f"time {table['total']:.1f} s: ")


def test_an_unknown_stage_is_refused():
    with pytest.raises(KeyError, match="unknown stage 'lunch'"):
        with TimeBudget(CompileLog()).stage("lunch"):
            pass


def test_the_budget_owns_the_training_clock_and_a_resume_continues_it():
    budget = TimeBudget()  # no compile log: compiles are not told apart, "compile" is None
    with budget.clock:
        time.sleep(0.02)
        with budget.clock.paused():
            time.sleep(0.05)  # e.g. a probe render: not training time
    assert 0.02 <= budget.clock.total < 0.05
    budget.resume_clock(100.0)  # a resumed run starts from its checkpoint's wall_s
    with budget.clock:
        time.sleep(0.01)
    assert 100.01 <= budget.clock.total < 100.05
    table = budget.as_dict()
    assert table["compile"] is None and table["compile_wait"] == 0.0 and " (compiling" not in budget.line()
