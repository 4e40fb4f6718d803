"""The compositor of two source trees on the same sorted inputs, in one process, alternated call by call;
prints JSON.

``--old-src DIR`` names another tree's ``src`` (e.g. a ``git worktree`` of an earlier revision); its
``cusgs_jax/splat/composite.py`` is loaded as a separate module (its imports resolve against this tree's
package, so trees whose compositor imports the same helpers compare). On the sorted inputs of a scene's first
view (``composite_profile.sorted_inputs``), with ``--channels`` extra random channels appended, it times the
forward and the forward+backward (random cotangents) of both, alternately, and reports the medians, the median
per-call ratio old/new and how far the outputs are apart (max |Δ| relative to the largest value).

    git worktree add --detach /tmp/old c806fe4
    python benchmarks/composite_compare.py --old-src /tmp/old/src --scene demo --channels 0 48
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import pathlib
import time


def load_compositor(src: pathlib.Path):
    spec = importlib.util.spec_from_file_location("old_composite", src / "cusgs_jax" / "splat" / "composite.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.composite_tiles


def main(argv=None):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from composite_profile import sorted_inputs
    from cusgs_jax.splat.composite import composite_tiles, default_lanes

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--old-src", type=pathlib.Path, required=True)
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--channels", type=int, nargs="+", default=[0])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    compositors = {"old": load_compositor(args.old_src), "new": composite_tiles}
    grid, inputs, info = sorted_inputs(args.scene, 0)
    chunk, lanes = info["chunk_default"], default_lanes(grid.num_tiles)
    rows = []
    for extra in args.channels:
        rng = np.random.default_rng(0)
        features = np.concatenate([inputs[3], rng.normal(size=(inputs[3].shape[0], extra)).astype(np.float32)], 1)
        call = [jnp.asarray(x) for x in (*inputs[:3], features, *inputs[4:])]
        fns, outs = {}, {}
        shape = (grid.num_tiles, grid.tile_size ** 2)
        ct_c = jnp.asarray(rng.normal(size=shape + (features.shape[1],)).astype(np.float32))
        ct_t = jnp.asarray(rng.normal(size=shape).astype(np.float32))
        for name, fn in compositors.items():
            forward = jax.jit(lambda *a, fn=fn: fn(grid, chunk, lanes, *a))

            def loss(m, c, o, f, *rest, fn=fn):
                r = fn(grid, chunk, lanes, m, c, o, f, *rest)
                return jnp.sum(r.colors * ct_c) + jnp.sum(r.transmittance * ct_t)

            both = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))
            fns[name] = (forward, both)
            outs[name] = jax.device_get((forward(*call), both(*call)))
        times = {(name, part): [] for name in fns for part in ("forward", "forward_backward")}
        for _ in range(args.repeats):
            for name, (forward, both) in fns.items():
                for part, fn in (("forward", forward), ("forward_backward", both)):
                    start = time.perf_counter()
                    jax.block_until_ready(fn(*call))
                    times[(name, part)].append(time.perf_counter() - start)

        def apart(a, b):
            a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
            return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-30))

        (f_old, g_old), (f_new, g_new) = outs["old"], outs["new"]
        row = dict(channels=int(features.shape[1]),
                   colors_apart=apart(f_old.colors, f_new.colors),
                   gradients_apart=max(apart(a, b) for a, b in zip(g_old, g_new)),
                   n_contrib_equal=bool(np.array_equal(f_old.n_contrib, f_new.n_contrib)))
        for part in ("forward", "forward_backward"):
            old, new = np.asarray(times[("old", part)]), np.asarray(times[("new", part)])
            row[f"{part}_ms_old"] = 1e3 * float(np.median(old))
            row[f"{part}_ms_new"] = 1e3 * float(np.median(new))
            row[f"{part}_ratio_old_over_new"] = float(np.median(old / new))
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(json.dumps(dict(benchmark="composite_compare", old_src=str(args.old_src), **info, jax=jax.__version__,
                          rows=rows), indent=1))


if __name__ == "__main__":
    main()
