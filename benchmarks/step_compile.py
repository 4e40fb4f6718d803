"""Lowering and compile time of the default demo run's training step, and the size of its program.

Sets a run up as ``cusgs-train`` does with the given overrides, then times
``make_train_step(...).lower(state, batch)`` and ``.compile()`` of the first step, and counts
the lines of its StableHLO and optimised HLO, its while loops and fusions. Prints one JSON line.

    python benchmarks/step_compile.py features=none   # RGB only
    python benchmarks/step_compile.py                 # the default demo run (RGB + feature models)
"""

from __future__ import annotations

import json
import sys
import tempfile
import time

from cusgs_jax.app import loop as run_loop
from cusgs_jax.app.session import setup
from cusgs_jax.compose import compose_config
from cusgs_jax.training.step import make_train_step


def main(overrides: list[str]) -> dict:
    session = setup(compose_config(["train.progress=false", *overrides]), tempfile.mkdtemp())
    loop = run_loop.start(session)
    batch = session.batches(0)
    step = make_train_step(session.cfg, loop.tx, session.strategies, loop.capacities)
    t0 = time.perf_counter()
    lowered = step.lower(loop.state, batch)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    hlo = compiled.as_text()
    return dict(overrides=overrides, lower_s=round(t1 - t0, 2), compile_s=round(t2 - t1, 2),
                stablehlo_lines=lowered.as_text().count("\n"), hlo_lines=hlo.count("\n"),
                while_loops=hlo.count(" while("), fusions=hlo.count("fusion("))


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:])))
