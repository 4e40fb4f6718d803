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

from cusgs_jax.data.colmap import load_scene
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.train import ModelConfig, TrainConfig, init_train_state, make_train_step


def _feature_config():
    from omegaconf import OmegaConf

    from cusgs_jax.runner import feature_config

    path = os.path.join(os.path.dirname(__import__("cusgs_jax").__file__), "conf", "features", "demo.yaml")
    return feature_config(OmegaConf.to_container(OmegaConf.load(path)))


def bench(width: int, height: int, steps: int, views: int, voxel_size: float, features: bool) -> dict:
    from cusgs_jax.runner import load_feature_targets

    cfg = TrainConfig(iterations=30_000, model=ModelConfig(voxel_size=voxel_size),
                      **({"features": _feature_config()} if features else {}))
    with tempfile.TemporaryDirectory() as tmp:
        scene = load_scene(generate_demo_scene(os.path.join(tmp, "demo"), num_views=views, width=width,
                                               height=height), holdout_every=0)
        banks, targets = None, {}
        if features:
            maps, banks = load_feature_targets(cfg.features, scene, 0, auto_extract=True)
            banks = {k: jnp.asarray(v) for k, v in banks.items()}
            targets = {k: jnp.asarray(fs.maps.astype(np.float16)) for k, fs in maps.items()}
    state, tx = init_train_state(cfg, scene.points, len(scene.names), scene.extent, banks)
    step = make_train_step(cfg, tx, width, height)
    images = jnp.asarray(scene.images.astype(np.float32) / 255.0)

    def batch(i):
        v = i % len(scene.names)
        b = dict(image=images[v], viewmat=jnp.asarray(scene.viewmats[v]), K=jnp.asarray(scene.Ks[v]),
                 index=jnp.int32(v))
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
    parser.add_argument("--voxel-size", type=float, default=0.04)
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
