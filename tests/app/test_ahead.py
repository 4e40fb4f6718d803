"""app/ahead.py: programs compiled on a background thread run the same numbers, and only for their types."""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.app.ahead import Ahead, Program, signature
from cusgs_jax.app.budget import TimeBudget
from cusgs_jax.app.compiles import CompileLog


def _update(state, x, scale):
    """A stand-in step: state {"w": [N], "n": [] int32} updated by x [N] and a Python scalar."""
    return dict(w=jnp.tanh(state["w"] * scale + x), n=state["n"] + 1), jnp.sum(state["w"] * x)


def _state(n=5):
    return dict(w=jnp.linspace(-1.0, 1.0, n), n=jnp.int32(0))


def test_a_prepared_program_gives_the_jitted_numbers_with_donation_and_counts_as_background():
    step = jax.jit(_update, donate_argnums=0)
    reference = jax.jit(_update)(_state(), jnp.ones(5), 3)
    waits = []
    with CompileLog() as log, Ahead(on_wait=waits.append) as ahead:
        program = Program(step, ahead)
        assert program.prepare(_state(), jnp.ones(5), 2)  # another value of the scalar: the same program
        assert not program.prepare(_state(), jnp.ones(5), 7)  # already under way
        state = _state()
        out, total = program(state, jnp.ones(5), 3)
    np.testing.assert_array_equal(out["w"], reference[0]["w"])
    assert int(out["n"]) == 1 and float(total) == float(reference[1])
    assert state["w"].is_deleted()  # donated, as the jitted call donates
    assert program.fallbacks == 0 and ahead.submitted == 1 and len(waits) == ahead.waits <= 1
    background = [r for r in log.records if r["background"]]
    assert len(background) == 1 and "update" in background[0]["function"]
    assert log.foreground_seconds < log.seconds


def test_arguments_of_other_types_run_the_jitted_function():
    step = jax.jit(_update)
    with Ahead() as ahead:
        program = Program(step, ahead)
        program.prepare(_state(5), jnp.ones(5), 1)
        out, _ = program(_state(7), jnp.ones(7), 1)  # not prepared for 7: the jitted call compiles it
        assert out["w"].shape == (7,) and program.fallbacks == 0
        # an executable that refuses what it is handed (as one compiled for other shardings would): the call
        # is refused before anything runs, and the jitted function gives the answer
        key = signature((_state(6), jnp.ones(6), 1))
        program._ready[key] = step.lower(_state(5), jnp.ones(5), 1).compile()
        out, _ = program(_state(6), jnp.ones(6), 1)
    assert out["w"].shape == (6,) and program.fallbacks == 1
    np.testing.assert_array_equal(out["w"], step(_state(6), jnp.ones(6), 1)[0]["w"])


def test_the_signature_is_shapes_and_types_not_values():
    a = signature((_state(3), jnp.ones(3), 2))
    assert a == signature((_state(3), jnp.zeros(3), 9))
    assert a != signature((_state(4), jnp.ones(4), 2))
    assert a != signature((_state(3), jnp.ones(3), 2.0))  # a Python float traces as another type
    assert a != signature((_state(3), jnp.ones(3, jnp.float16), 2))


def test_a_wait_for_a_background_compile_is_compile_wait_and_its_seconds_are_not():
    import time

    with CompileLog() as log:
        budget = TimeBudget(log)
        with Ahead(on_wait=budget.waited, workers=1, delay_s=0.3) as ahead:  # the compile is under way for 0.3 s
            program = Program(jax.jit(lambda x: jnp.cos(x) * 3.0), ahead)
            program.prepare(jnp.ones(11))
            time.sleep(0.05)  # the compile thread has taken it (a running compile cannot leave the queue)
            with budget.stage("train_steps"):
                program(jnp.ones(11)).block_until_ready()
        table = budget.as_dict()
    assert table["compile_wait"] >= 0.25 and ahead.waits == 1
    assert table["compile"] == pytest.approx(log.seconds, abs=1e-3)
    parts = sum(v for k, v in table.items() if k not in ("total", "compile"))
    assert parts == pytest.approx(table["total"], abs=0.005)


def test_disabled_compiles_nothing_ahead():
    with Ahead(enabled=False) as ahead:
        program = Program(jax.jit(jnp.sin), ahead)
        assert not program.prepare(jnp.ones(3))
        np.testing.assert_array_equal(program(jnp.ones(3)), jnp.sin(jnp.ones(3)))
    assert ahead.submitted == 0


def test_settle_waits_for_every_compile_submitted_and_charges_one_wait():
    release = threading.Event()
    waits = []
    with Ahead(on_wait=waits.append, workers=1) as ahead:
        blocker = ahead._pool.submit(release.wait)  # the thread is busy: both compiles queue behind it
        first, second = Program(jax.jit(jnp.sin), ahead), Program(jax.jit(jnp.cos), ahead)
        assert first.prepare(jnp.ones(4)) and second.prepare(jnp.ones(4))
        threading.Timer(0.3, release.set).start()
        ahead.settle()
        assert all(future.done() for future in second._pending.values())  # both compiled: the calls wait for nothing
        assert len(waits) == 1 and waits[0] >= 0.25
        np.testing.assert_array_equal(second(jnp.ones(4)), jnp.cos(jnp.ones(4)))
        ahead.settle()  # nothing left: no wait
        blocker.result()
    assert len(waits) == 1 and ahead.waits == 1


def test_two_compiles_run_side_by_side_until_settle_narrows_them_to_one():
    """The start's step and evaluation render compile at once; after ``settle(workers=1)`` (the loop on a CPU)
    one compile at a time, and a program prepared then still gives the jitted numbers."""
    with Ahead() as ahead:
        assert ahead.workers == 2
        both = threading.Barrier(2, timeout=10)  # passes only when two tasks wait at once
        for future in [ahead._pool.submit(both.wait) for _ in range(2)]:
            future.result()
        ahead.settle(workers=1)
        assert ahead.workers == 1
        one = threading.Barrier(2, timeout=0.3)
        first, second = (ahead._pool.submit(one.wait) for _ in range(2))
        with pytest.raises(threading.BrokenBarrierError):  # the second never started beside the first
            first.result()
        with pytest.raises(threading.BrokenBarrierError):
            second.result()
        program = Program(jax.jit(jnp.sin), ahead)
        assert program.prepare(jnp.ones(4))
        np.testing.assert_array_equal(program(jnp.ones(4)), jnp.sin(jnp.ones(4)))
    assert ahead.submitted == 1 and program.fallbacks == 0


def test_an_accelerator_compiles_several_programs_at_once_where_the_host_has_idle_cores():
    from cusgs_jax.app.ahead import WORKERS, default_workers

    assert default_workers("cpu", 64) == WORKERS
    assert default_workers("gpu", 16) == 4 and default_workers("gpu", 4) == WORKERS and default_workers("tpu", 12) == 3


def test_a_program_needed_while_queued_behind_others_compiles_at_once_on_the_callers_thread():
    """One compile thread busy (a slow compile), a second program queued behind it: the caller that needs the second
    does not wait for the first — its compile leaves the queue and runs on the caller's thread."""
    import threading
    import time

    import jax
    import jax.numpy as jnp

    from cusgs_jax.app.ahead import Ahead, Program

    release = threading.Event()
    with Ahead(workers=1) as ahead:
        ahead._pool.submit(release.wait, 30)  # the only thread, busy until released
        program = Program(jax.jit(jnp.tanh), ahead)
        program.prepare(jnp.ones(5))
        started = time.perf_counter()
        np.testing.assert_array_equal(program(jnp.ones(5)), jnp.tanh(jnp.ones(5)))
        assert time.perf_counter() - started < 20 and ahead.waits == 1
        release.set()
