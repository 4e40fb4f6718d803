"""What rasterising through a lens costs (``data.undistort=lens``); prints JSON.

For every (G, resolution) cell the same Gaussians and camera are drawn three ways — pinhole, through
the demo's OPENCV lens and through an OPENCV_FISHEYE lens (``splat/lens.py``) — forward and
forward+backward, compiled once each and timed interleaved (pinhole call i, OPENCV call i, fisheye
call i, …) so load on the shared machine affects them alike. Each row gives the medians and the
ratio to the pinhole's; the pair capacity is sized on the pinhole render and shared (the lenses
here move the footprints by a few pixels).

    python benchmarks/lens_bench.py [--gaussians 10000 50000 200000] [--sizes 128 256 512] [--repeats 7]
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
from scenes import random_scene  # noqa: E402

from cusgs_jax.splat import rasterize  # noqa: E402
from cusgs_jax.splat.lens import Lens  # noqa: E402

KEYS = ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")
LENSES = {  # the lens demo's OPENCV coefficients (data/demo/lens.py) and a mild fisheye; boxes wide enough
    "pinhole": None,
    "opencv": Lens(jnp.asarray([0.09, 0.02, 0, 0, 0.001, -0.0015], jnp.float32), jnp.asarray([-3.0, 3, -3, 3])),
    "fisheye": Lens(jnp.asarray([0.05, -0.01, 0.003, -0.001, 0, 0], jnp.float32), jnp.asarray([-3.0, 3, -3, 3]),
                    fisheye=True),
}


def _programs(scene, size, max_pairs):
    args = [jnp.asarray(scene[k]) for k in KEYS]
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(size, size, scene["colors"].shape[1])), jnp.float32)
    programs, compile_s = {}, {}
    for name, lens in LENSES.items():
        def render(*a, lens=lens):
            return rasterize(*a, size, size, tile_size=8, max_pairs=max_pairs, lens=lens).image

        def loss(*a, render=render):
            return jnp.sum(render(*a) * weights)

        for kind, fn in (("forward", render), ("forward_backward", jax.grad(loss, argnums=(0, 1, 2, 3, 4)))):
            start = time.perf_counter()
            compiled = jax.jit(fn).lower(*args).compile()
            compile_s[(name, kind)] = time.perf_counter() - start
            jax.block_until_ready(compiled(*args))  # warm-up
            programs[(name, kind)] = compiled
    return args, programs, compile_s


def run(gaussians, sizes, repeats):
    rows = []
    for num in gaussians:
        for size in sizes:
            scene = random_scene(num, size, size)
            args = [jnp.asarray(scene[k]) for k in KEYS]
            probe = rasterize(*args, size, size, tile_size=8, max_pairs=40 * num)
            max_pairs = int(1.25 * int(probe.num_pairs)) + 1024
            args, programs, compile_s = _programs(scene, size, max_pairs)
            times = {key: [] for key in programs}
            for _ in range(repeats):
                for key, fn in programs.items():
                    start = time.perf_counter()
                    jax.block_until_ready(fn(*args))
                    times[key].append(time.perf_counter() - start)
            for kind in ("forward", "forward_backward"):
                base = float(np.median(times[("pinhole", kind)]))
                for name in LENSES:
                    median = float(np.median(times[(name, kind)]))
                    row = dict(gaussians=num, width=size, height=size, pass_=kind, camera=name, median_s=median,
                               ratio_to_pinhole=median / base, compile_s=compile_s[(name, kind)], repeats=repeats)
                    rows.append(row)
                    print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rows = run(args.gaussians, args.sizes, args.repeats)
    print(json.dumps(dict(benchmark="lens_bench", device=jax.devices()[0].device_kind, backend=jax.default_backend(),
                          machine=platform.machine(), cpus=os.cpu_count(), rows=rows), indent=1))


if __name__ == "__main__":
    main()
