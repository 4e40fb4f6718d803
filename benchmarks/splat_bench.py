"""Speed and memory of ``cusgs_jax.splat.rasterize``; prints JSON.

For every (G, resolution) cell: compile time, median forward and
forward+backward time, XLA's peak-memory estimate of the compiled program
(arguments + outputs + temporaries, from ``compiled.memory_analysis()``), the
number of composited pixel–Gaussian pairs and pairs per second. Variants
(tile size, chunk size) and the naive baseline of ``naive_splat.py`` run side
by side in one process so their ratios are comparable.

With ``--backends jax pallas`` every cell is timed with each compositor (``rasterize(backend=...)``)
and each row after the first backend's carries ``image_rel_diff`` and ``grad_rel_diff``:
‖ours − first‖ / ‖first‖ of the image and of each input's gradient (the largest), on the same inputs.

Usage:
  python benchmarks/splat_bench.py                 # full grid, tile 8 and 16
  python benchmarks/splat_bench.py --gaussians 500000 --sizes 1024 --tile-sizes 16 --backends jax pallas
  python benchmarks/splat_bench.py --quick         # 50k × {128², 256²} + naive
  python benchmarks/splat_bench.py --gaussians 50000 --sizes 128 --naive
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from naive_splat import naive_rasterize  # noqa: E402
from scenes import random_scene  # noqa: E402
from timing import median_seconds  # noqa: E402

from cusgs_jax.splat import Compositor, rasterize  # noqa: E402

KEYS = ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")


def _peak_bytes(compiled):
    mem = compiled.memory_analysis()
    if mem is None:
        return None
    return int(mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes)


def measure(render, scene, repeats, outputs=None):
    """Compile, time and size one renderer ``render(*arrays) -> image``; with ``outputs`` (a dict),
    also keep its image and gradients there (``outputs["forward"]``, ``outputs["forward_backward"]``)."""
    args = [jnp.asarray(scene[k]) for k in KEYS]
    weights = jnp.asarray(np.random.default_rng(1).normal(
        size=(scene["height"], scene["width"], scene["colors"].shape[1])).astype(np.float32))

    def loss(*a):
        return jnp.sum(render(*a) * weights)

    result = {}
    for name, fn in (("forward", render), ("forward_backward", jax.grad(loss, argnums=(0, 1, 2, 3, 4)))):
        start = time.perf_counter()
        compiled = jax.jit(fn).lower(*args).compile()
        result[f"{name}_compile_s"] = time.perf_counter() - start
        value = jax.block_until_ready(compiled(*args))  # warm-up
        if outputs is not None:
            outputs[name] = value
        result[f"{name}_median_s"] = median_seconds(compiled, args, repeats)
        result[f"{name}_peak_bytes"] = _peak_bytes(compiled)
    return result


def _rel_diff(ours, reference) -> float:
    ours, reference = np.asarray(ours, np.float64), np.asarray(reference, np.float64)
    return float(np.linalg.norm(ours - reference) / max(np.linalg.norm(reference), 1e-30))


def run(gaussians, sizes, tile_sizes, chunk_sizes, naive, repeats, backends=("auto",)):
    rows = []
    for num in gaussians:
        for size in sizes:
            scene = random_scene(num, size, size)
            args = [jnp.asarray(scene[k]) for k in KEYS]
            for tile_size in tile_sizes:
                # Size the pair capacity to the scene, as a user would after one
                # render (jax-md style): 1.25x the pairs found with a generous capacity.
                probe = rasterize(*args, size, size, tile_size=tile_size, max_pairs=40 * num)
                max_pairs = int(1.25 * int(probe.num_pairs)) + 1024
                first = None
                for chunk, backend in [(c, b) for c in chunk_sizes for b in backends]:
                    def render(*a, ts=tile_size, ch=chunk, mp=max_pairs, be=backend):
                        return rasterize(*a, size, size, tile_size=ts, max_pairs=mp, compositor=Compositor(be, ch)).image

                    row = dict(renderer="cusgs_jax", backend=backend, gaussians=num, width=size, height=size,
                               tile_size=tile_size, chunk_size=chunk, max_pairs=max_pairs)
                    outputs = {}
                    try:
                        row.update(measure(render, scene, repeats, outputs))
                    except Exception as error:  # noqa: BLE001 — one failing variant must not hide the others
                        row["error"] = f"{type(error).__name__}: {str(error)[:2000]}"
                        rows.append(row)
                        print(json.dumps(row), file=sys.stderr, flush=True)
                        continue
                    if first is None:
                        first = outputs
                    elif len(backends) > 1:
                        row.update(image_rel_diff=_rel_diff(outputs["forward"], first["forward"]),
                                   grad_rel_diff=max(_rel_diff(a, b) for a, b in
                                                     zip(outputs["forward_backward"], first["forward_backward"])))
                    out = rasterize(*args, size, size, tile_size=tile_size, max_pairs=max_pairs,
                                    compositor=Compositor(backend, chunk))
                    composited = int(jnp.sum(out.n_contrib))
                    row.update(
                        tile_pairs=int(out.num_pairs), overflow=int(out.overflow),
                        composited_pairs=composited,
                        forward_pairs_per_s=composited / row["forward_median_s"],
                        forward_backward_pairs_per_s=composited / row["forward_backward_median_s"],
                    )
                    rows.append(row)
                    print(json.dumps(row), file=sys.stderr, flush=True)
            if naive and num <= 50_000 and size <= 256:
                def render_naive(*a):
                    return naive_rasterize(*a, size, size)

                row = dict(renderer="naive_topk256", gaussians=num, width=size, height=size,
                           tile_size=16, chunk_size=None)
                row.update(measure(render_naive, scene, repeats))
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--tile-sizes", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--chunk-sizes", type=int, nargs="+", default=[16])
    parser.add_argument("--naive", action="store_true",
                        help="also time the naive baseline (cells up to 50k and 256² only: it needs O(G·tiles) memory)")
    parser.add_argument("--quick", action="store_true", help="50k × {128², 256²} with the naive baseline")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backends", nargs="+", default=["auto"], choices=["auto", "jax", "pallas"],
                        help="compositors to time at every cell (rasterize(backend=...))")
    args = parser.parse_args(argv)
    if args.quick:
        args.gaussians, args.sizes, args.naive = [50_000], [128, 256], True
    rows = run(args.gaussians, args.sizes, args.tile_sizes, args.chunk_sizes, args.naive, args.repeats,
               tuple(args.backends))
    report = dict(
        benchmark="splat",
        jax=jax.__version__, backend=jax.default_backend(), device=str(jax.devices()[0]),
        machine=platform.machine(), cpu_count=os.cpu_count(), results=rows,
    )
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
