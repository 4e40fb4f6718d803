"""Channels composited at a few pixels per tile (``composite_tiles(sparse=, sparse_slots=)``, what the train step
does for the queries of feature maps coarser than the image) against compositing them everywhere; prints JSON.

On the sorted inputs of a scene's first view (``composite_profile.sorted_inputs``), with Q random extra channels
read at the image pixels nearest the centres of a feature map of 1/``stride`` the image's resolution (the pixels
the feature loss reads): forward+backward of the dense compositor (RGB + depth + Q channels everywhere) and of
the sparse one (RGB + depth everywhere, Q at the listed pixels), alternated call by call, median of
``--repeats``, and the median of the per-call ratios.

    python benchmarks/sparse_channels.py --scene demo --channels 48 96 --stride 2 4 8 16
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from composite_profile import sorted_inputs
    from cusgs_jax.model.field import read_pixels
    from cusgs_jax.splat.composite import composite_tiles, default_lanes
    from cusgs_jax.splat.render import SparseChannels

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--channels", type=int, nargs="+", default=[48])
    parser.add_argument("--stride", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--repeats", type=int, default=11)
    args = parser.parse_args(argv)
    grid, inputs, info = sorted_inputs(args.scene, 0)
    base = [jnp.asarray(x) for x in inputs]
    chunk, lanes = info["chunk_default"], default_lanes(grid.num_tiles)
    rows = []
    for q in args.channels:
        extra = jnp.asarray(np.random.default_rng(5).normal(size=(base[0].shape[0], q)).astype(np.float32))
        for stride in args.stride:
            feature_hw = {"map": (max(1, grid.height // stride), max(1, grid.width // stride))}
            pixels = read_pixels(feature_hw, (grid.height, grid.width), max_fraction=1.0)  # what the loss reads
            slots = jnp.asarray(SparseChannels(q, pixels).slots(grid)[0])

            def dense(m, co, o, f, e):
                out = composite_tiles(grid, chunk, lanes, m, co, o, jnp.concatenate([f, e], -1), *base[4:])
                return jnp.sum(out.colors) + jnp.sum(out.transmittance)

            def sparse(m, co, o, f, e):
                out = composite_tiles(grid, chunk, lanes, m, co, o, f, *base[4:], e, slots)
                return jnp.sum(out.colors) + jnp.sum(out.sparse) + jnp.sum(out.transmittance)

            fns = {name: jax.jit(jax.grad(fn, argnums=(0, 1, 2, 3, 4))) for name, fn in (("dense", dense),
                                                                                       ("sparse", sparse))}
            call = base[:4] + [extra]
            for fn in fns.values():
                jax.block_until_ready(fn(*call))
            times = {name: [] for name in fns}
            for _ in range(args.repeats):
                for name, fn in fns.items():
                    start = time.perf_counter()
                    jax.block_until_ready(fn(*call))
                    times[name].append(time.perf_counter() - start)
            ratios = np.asarray(times["dense"]) / np.asarray(times["sparse"])
            rows.append(dict(channels=q, stride=stride, listed_pixels=len(pixels), listed_per_tile=int(slots.shape[1]),
                             dense_ms=1e3 * float(np.median(times["dense"])),
                             sparse_ms=1e3 * float(np.median(times["sparse"])),
                             dense_over_sparse=float(np.median(ratios))))
            print(json.dumps(rows[-1]), flush=True)
    print(json.dumps(dict(benchmark="sparse_channels", **info, jax=jax.__version__, rows=rows), indent=1))


if __name__ == "__main__":
    main()
