"""Wall time of a run's steps with its strategy updates, by blocks of 100 steps, for this revision or an older one;
prints JSON.

The loop of ``cusgs-train`` without evaluations, checkpoints or compiling ahead: each step replayed until it drops no
work (``exact_step``), then the strategies that are due (``run_strategies``). Run it once per revision, alternately, with
that revision's ``src/`` on ``PYTHONPATH`` (a ``git worktree`` of the older one); revisions up to 0bdb18c (whose
``setup`` returned one mutable session) are driven through their own API.

    PYTHONPATH=<tree>/src python benchmarks/loop_steps.py --steps 1000 data.path=<scene> features=none ...
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np


def _driver(cfg):
    """(batches, step, densify, state, capacities) callables over this revision's run loop."""
    try:
        from cusgs_jax.app import loop as run_loop
        from cusgs_jax.app.session import setup
    except ImportError:  # up to 0bdb18c: app/run.py's setup returns a mutable Session holding the state
        from cusgs_jax.app import run as run_loop

        session = run_loop.setup(cfg, tempfile.mkdtemp())
        clock = session.clock
        return (clock, run_loop._batches(session), lambda b: run_loop._exact_step(session, b),
                lambda s: run_loop._densify(session, s), lambda: session.state, lambda: session.capacities)
    session = setup(cfg, tempfile.mkdtemp())
    loop = run_loop.start(session)
    step = getattr(run_loop, "exact_step", None) or run_loop._exact_step  # public since the library API
    densify = getattr(run_loop, "run_strategies", None) or run_loop._densify
    return (session.budget.clock, session.batches, lambda b: step(session, loop, b),
            lambda s: densify(session, loop, s), lambda: loop.state, lambda: loop.capacities)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("overrides", nargs="*", help="cusgs-train overrides (data.path=..., features=none, ...)")
    args = parser.parse_args()
    try:
        from cusgs_jax.compose import compose_config
    except ImportError:  # older revisions
        from cusgs_jax.config import compose_config
    cfg = compose_config(["train.progress=false", *args.overrides])
    clock, batches, step, densify, state, capacities = _driver(cfg)
    blocks = []
    with clock:  # a strategy's probe pauses the run's clock
        step(batches(0))  # compiles
        start = time.perf_counter()
        for done in range(1, args.steps):
            step(batches(done))
            densify(done + 1)
            if done % 100 == 99:
                blocks.append(round((time.perf_counter() - start) * 10, 1))
                start = time.perf_counter()
    anchors = state().anchors
    print(json.dumps(dict(ms_per_step_by_100=blocks, alive=int(np.sum(np.asarray(anchors.alive))),
                          capacity=int(anchors.capacity), capacities=str(capacities()))))


if __name__ == "__main__":
    main()
