"""Train-step time for B ∈ {1, 2, 4} views per step on 1 and on 2 devices (the demo scene, RGB); prints JSON.

Runs in one process with ``--devices`` virtual CPU devices (``XLA_FLAGS=--xla_force_host_platform_device_count``,
set here before JAX starts); every variant starts from the same state (the demo scaffold after
initialisation) and the variants' steps are timed interleaved (variant 1 step i, variant 2 step i, …), so
other load on the machine affects them alike. Each row: compile seconds, median step seconds, median
seconds per view (step / B), and ``ratio`` = its seconds per view over B = 1 on 1 device.

On a CPU the virtual devices share the same cores: two devices are not two processors' worth of
compute, so this measures the cost of the sharded program (partitioning, the gradient all-reduce,
gathering the views' statistics), not a speed-up. On a machine with several accelerators the same
command with ``--real-devices`` times the real ones.

    python benchmarks/sharded_bench.py [--steps 10] [--batch-sizes 1 2 4] [--devices 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--devices", type=int, default=2, help="virtual CPU devices (ignored with --real-devices)")
    parser.add_argument("--real-devices", action="store_true", help="use the accelerators present")
    args = parser.parse_args()
    if not args.real_devices:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + f" --xla_force_host_platform_device_count={args.devices}").strip()
    import jax
    import numpy as np

    from cusgs_jax.training.inputs import view_order
    from cusgs_jax.config import Config, DataConfig
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.demo import generate_demo_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.densify.factory import make_strategies
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.training.step import make_train_step
    from cusgs_jax.types import Camera

    scene_path = generate_demo_scene(os.path.join(tempfile.mkdtemp(), "demo"))
    scene, _ = normalize_scene(load_scene(scene_path, DataConfig(format="colmap")))
    idx = scene.train_indices
    images = np.asarray(scene.images[idx], np.float32) / 255.0
    base = resolve_voxel_size(Config().replace(train=dict(iterations=30_000)), scene.points)

    variants = []
    for batch_size in args.batch_sizes:
        for devices in sorted({1, min(jax.device_count(), batch_size)}):
            if batch_size % devices:
                continue
            cfg = base.replace(train=dict(batch_size=batch_size, devices=str(devices)))
            strategies = make_strategies(cfg)
            state, tx = init_train_state(cfg, scene.points, len(idx), scene.extent, strategies)
            variants.append(dict(batch_size=batch_size, devices=devices, state=state,
                                 step=make_train_step(cfg, tx, strategies), times=[]))

    def batch(batch_size: int, i: int) -> dict:
        views = np.array([view_order(0, len(idx), i * batch_size + b) for b in range(batch_size)])
        if batch_size == 1:
            views = views[0]
        return dict(image=images[views], camera=Camera(scene.Ks[idx][views].astype(np.float32),
                                                       scene.viewmats[idx][views].astype(np.float32),
                                                       scene.width, scene.height),
                    index=np.asarray(views, np.int32))

    for v in variants:  # compile (first call) outside the timed steps
        start = time.perf_counter()
        v["state"], metrics = v["step"](v["state"], batch(v["batch_size"], 0))
        jax.block_until_ready(metrics)
        v["compile_s"] = time.perf_counter() - start
    for i in range(1, args.steps + 1):
        for v in variants:
            start = time.perf_counter()
            v["state"], metrics = v["step"](v["state"], batch(v["batch_size"], i))
            jax.block_until_ready(metrics)
            v["times"].append(time.perf_counter() - start)
    rows = []
    for v in variants:
        step_s = float(np.median(v["times"]))
        rows.append(dict(batch_size=v["batch_size"], devices=v["devices"], compile_s=round(v["compile_s"], 2),
                         step_s=round(step_s, 4), s_per_view=round(step_s / v["batch_size"], 4)))
    reference = rows[0]["s_per_view"]
    for row in rows:
        row["ratio"] = round(row["s_per_view"] / reference, 3)
    print(json.dumps(dict(
        benchmark="sharded_train_step", scene=f"demo {scene.width}x{scene.height}, {len(idx)} train views",
        anchors=int(np.sum(variants[0]["state"].anchors.alive)), steps=args.steps,
        device_kind=jax.devices()[0].device_kind, device_count=jax.device_count(), cpu_count=os.cpu_count(),
        platform=platform.platform(), python=sys.version.split()[0], jax=jax.__version__, rows=rows), indent=1))


if __name__ == "__main__":
    main()
