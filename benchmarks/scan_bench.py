"""Integer running sums, maxima and ``nonzero`` with a size: XLA's reduce-window forms against scan.py's parallel
prefix, alternately, at the step's sizes; prints JSON (median ms of each, and their ratio per size).

    python benchmarks/scan_bench.py [--sizes 20000 100000 400000] [--repeats 30]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.scan import first_true, running_max, running_sum


def _time(fn, x, repeats: int) -> list[float]:
    fn(x).block_until_ready()
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(x).block_until_ready()
        out.append((time.perf_counter() - start) * 1e3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20_000, 100_000, 400_000])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    rng, rows = np.random.default_rng(0), []
    for n in args.sizes:
        values = jnp.asarray(rng.integers(0, 1000, n).astype(np.int32))
        mask = jnp.asarray(rng.uniform(size=n) < 0.4)
        size = n // 2
        pairs = {
            "sum": (jax.jit(jnp.cumsum), jax.jit(running_sum), values),
            "max": (jax.jit(jax.lax.cummax), jax.jit(running_max), values),
            "nonzero": (jax.jit(lambda m: jnp.nonzero(m, size=size, fill_value=0)[0].astype(jnp.int32)),
                        jax.jit(lambda m: first_true(m, size)), mask),
        }
        for name, (xla, scan, x) in pairs.items():
            np.testing.assert_array_equal(xla(x), scan(x))  # the same values
            old, new = [], []
            for _ in range(3):  # alternated rounds
                old += _time(xla, x, args.repeats // 3)
                new += _time(scan, x, args.repeats // 3)
            rows.append(dict(n=n, op=name, xla_ms=round(statistics.median(old), 4),
                             scan_ms=round(statistics.median(new), 4),
                             speedup=round(statistics.median(old) / statistics.median(new), 2)))
    print(json.dumps(dict(backend=jax.default_backend(), rows=rows), indent=1))


if __name__ == "__main__":
    main()
