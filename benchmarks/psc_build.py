"""Wall time of a PSC bank build (cusgs_jax.memory.psc.build) on a clustered input; prints JSON.

The input is the one tests/memory/test_psc.py checks for the scan's invariants: ``--rows`` rows
in ``--dim`` dimensions drawn around ``--clusters`` Gaussian centres (noise 0.2), built at
``--gamma`` with the default chunk. Reports the median of ``--repeats`` builds after a first,
compiling one (its time is reported apart), and the entry count (50 at the defaults).

    python benchmarks/psc_build.py [--rows 40000] [--dim 32] [--gamma 0.8] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import numpy as np

from cusgs_jax.memory import psc


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=40_000)
    ap.add_argument("--dim", type=int, default=32)
    ap.add_argument("--clusters", type=int, default=50)
    ap.add_argument("--gamma", type=float, default=0.8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=12)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    centres = rng.normal(size=(args.clusters, args.dim))
    x = (centres[rng.integers(0, args.clusters, args.rows)] + 0.2 * rng.normal(size=(args.rows, args.dim)))
    x = x.astype(np.float32)
    times = []
    for _ in range(args.repeats + 1):
        start = time.perf_counter()
        bank = psc.build(x, args.gamma)
        times.append(time.perf_counter() - start)
    result = dict(rows=args.rows, dim=args.dim, clusters=args.clusters, gamma=args.gamma, entries=bank.count,
                  first_build_s=round(times[0], 4), median_build_s=round(float(np.median(times[1:])), 4),
                  repeats=args.repeats, backend=jax.default_backend(), machine=platform.machine())
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
