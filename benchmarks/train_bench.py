"""Train-step speed on the demo scene at 1×, 2× and 4× its pixels; prints JSON.

For each resolution: compile time of the jitted step and the median step time
over ``--steps`` steps (after compilation), with the anchor count used; with
``--features`` also the same step with the demo feature field (daisy +
semantic, conf/features/demo.yaml), side by side in one process.

    python benchmarks/train_bench.py [--steps 20] [--views 12] [--features]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.app.inputs import load_feature_targets
from cusgs_jax.config import DEMO_FEATURE_MODELS, Config
from cusgs_jax.data.colmap import load_scene
from cusgs_jax.data.normalize import normalize_scene
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.densify.base import make_strategies
from cusgs_jax.training.state import init_train_state, resolve_voxel_size
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def bench(width: int, height: int, steps: int, views: int, voxel_size, features: bool) -> dict:
    cfg = Config().replace(train=dict(iterations=30_000), model=dict(voxel_size=voxel_size),
                           features=dict(models=DEMO_FEATURE_MODELS if features else ()))
    with tempfile.TemporaryDirectory() as tmp:
        scene, _ = normalize_scene(load_scene(generate_demo_scene(os.path.join(tmp, "demo"), num_views=views,
                                                                  width=width, height=height), holdout_every=0))
        cfg = resolve_voxel_size(cfg, scene.points)
        banks, targets = None, {}
        if features:
            maps, banks = load_feature_targets(cfg.features, scene, 0)
            banks = {k: jnp.asarray(v) for k, v in banks.items()}
            targets = {k: jnp.asarray(fs.maps.astype(np.float16)) for k, fs in maps.items()}
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, scene.points, len(scene.names), scene.extent, strategies, banks)
    step = make_train_step(cfg, tx, strategies)
    images = jnp.asarray(scene.images.astype(np.float32) / 255.0)

    def batch(i):
        v = i % len(scene.names)
        b = dict(image=images[v], camera=Camera.of_scene(scene, v), index=jnp.int32(v))
        if features:
            b["features"] = {k: t[v] for k, t in targets.items()}
            b["banks"] = banks
        return b

    start = time.perf_counter()
    state, metrics = step(state, batch(0))
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - start
    times = []
    for i in range(1, steps + 1):
        start = time.perf_counter()
        state, metrics = step(state, batch(i))
        jax.block_until_ready(metrics)
        times.append(time.perf_counter() - start)
    return dict(features=features, width=width, height=height, pixels=width * height,
                anchors=int(np.sum(state.anchors.alive)),
                capacity=state.anchors.capacity, compile_s=compile_s, median_step_s=float(np.median(times)),
                steps=steps)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--voxel-size", type=lambda v: v if v == "auto" else float(v), default="auto",
                        help="in units of the scene extent, or auto")
    parser.add_argument("--features", action="store_true", help="also time the step with the demo feature field")
    args = parser.parse_args(argv)
    rows = []
    for factor in (1, 2, 4):
        scale = math.sqrt(factor)
        width, height = int(round(160 * scale / 2) * 2), int(round(120 * scale / 2) * 2)
        for features in ((False, True) if args.features else (False,)):
            rows.append(dict(pixel_factor=factor,
                             **bench(width, height, args.steps, args.views, args.voxel_size, features)))
            print(json.dumps(rows[-1]), flush=True, file=__import__("sys").stderr)
    print(json.dumps(dict(benchmark="train_step", jax=jax.__version__, backend=jax.default_backend(),
                          cpu_count=os.cpu_count(), machine=platform.machine(), results=rows), indent=1))


if __name__ == "__main__":
    main()
