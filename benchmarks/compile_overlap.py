"""Does a compile beside the training steps buy wall time on this machine? One JSON line.

Sets a run up as ``cusgs-train`` does with the given overrides and compiles its first step. Then, ``--rounds``
times, it compiles the step for a new program (another tile-pair capacity: the same work to compile, shapes not
seen before) and runs ``--steps`` steps, two ways taken in turn:

* ``alone``: the compile on the calling thread, then the steps (what a run without compiling ahead does at a
  growth: it stands still, then goes on);
* ``beside``: the compile on the run's background thread (:class:`cusgs_jax.app.ahead.Ahead`, one worker, as a
  CPU run compiles after its start) while the same steps run.

Per way: the compile's seconds, the steps' seconds and the whole's (median over the rounds), and
``beside_over_alone``, the ratio of the wholes. Where the compile and the steps share the same cores (a 2-core CPU)
the ratio is near 1: compiling ahead then moves the wait into slower steps; where the steps run on an accelerator
it is below 1 by about the compile's share.

    python benchmarks/compile_overlap.py features=none --steps 150 --rounds 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp

from cusgs_jax.app import loop as run_loop
from cusgs_jax.app.ahead import Ahead, specs
from cusgs_jax.app.session import setup
from cusgs_jax.compose import compose_config
from cusgs_jax.training.step import make_train_step


@jax.jit
def _copy(tree):
    return jax.tree_util.tree_map(jnp.copy, tree)


def _steps(step, state, batches, count: int) -> float:
    start = time.perf_counter()
    for i in range(count):
        state, _ = step(state, batches(i))
    jax.block_until_ready(state)
    return time.perf_counter() - start


def main(overrides: list[str], steps: int, rounds: int) -> dict:
    session = setup(compose_config(["train.progress=false", "train.compilation_cache=null", *overrides]),
                    tempfile.mkdtemp())
    loop = run_loop.start(session)
    cfg, tx, batches = session.cfg, loop.tx, session.batches
    step = make_train_step(cfg, tx, session.strategies, loop.capacities)
    _steps(step, _copy(loop.state), batches, 3)  # compiled and warm
    types = specs((loop.state, batches(0)))
    rows = {"alone": [], "beside": []}
    with Ahead(workers=1) as ahead:
        for index in range(2 * rounds):
            way = "alone" if index % 2 == 0 else "beside"
            caps = dataclasses.replace(loop.capacities, pairs_per_active=loop.capacities.pairs_per_active + 0.5 * (index + 1))
            other = make_train_step(cfg, tx, session.strategies, caps)
            state = _copy(loop.state)
            jax.block_until_ready(state)
            start = time.perf_counter()
            if way == "alone":
                other.lower(*types).compile()
                compile_s = time.perf_counter() - start
                steps_s = _steps(step, state, batches, steps)
            else:
                future = ahead.compile(other, types)
                steps_s = _steps(step, state, batches, steps)
                future.result()
                compile_s = ahead.compile_seconds[-1]
            rows[way].append(dict(compile_s=compile_s, steps_s=steps_s, total_s=time.perf_counter() - start))
    median = {way: {key: round(statistics.median(r[key] for r in runs), 2) for key in ("compile_s", "steps_s", "total_s")}
              for way, runs in rows.items()}
    return dict(overrides=overrides, backend=jax.default_backend(), steps=steps, rounds=rounds, **median,
                beside_over_alone=round(median["beside"]["total_s"] / median["alone"]["total_s"], 3),
                totals={way: [round(r["total_s"], 2) for r in runs] for way, runs in rows.items()})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(main(args.overrides, args.steps, args.rounds)))
