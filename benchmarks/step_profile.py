"""Where one training step's time goes, by source line; prints JSON.

The initial model of a scene (as ``cusgs-train`` builds it, RGB only) takes ``--warmup`` steps,
then one step runs under ``jax.profiler``. Every XLA op's time is summed by JAX's trace path of the op (the ``op_name`` metadata of the
compiled HLO: which jitted function, forward or transpose, inside which loop), and the
costliest ops are listed with theirs — the per-stage table of ``scale_bench.py`` says which
stage, this says which op.

    python benchmarks/step_profile.py --scene demo
    python benchmarks/step_profile.py --features demo        # the default demo run's step (RGB + features)
    python benchmarks/step_profile.py --scene ~/.cache/cusgs_jax/scale_bench/<scene> --top 40
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import tempfile
import time


def build_with_features(features: str):
    """The demo's initial model as ``cusgs-train`` sets it up with feature models ``features``
    (``demo``: daisy, semantic and vgg16 stand-ins), its fitted capacities and its step."""
    from cusgs_jax.app import run
    from cusgs_jax.compose import from_dict
    from cusgs_jax.training.step import make_train_step

    cfg = from_dict(dict(train=dict(progress=False), features=dict(models=features)))  # the YAML spellings
    session = run.setup(cfg, tempfile.mkdtemp())
    loop = run.start(session)
    step = make_train_step(session.cfg, loop.tx, session.strategies, loop.capacities)
    return loop.state, step, session.batches


def build(scene_path: str):
    import jax.numpy as jnp
    import numpy as np

    from cusgs_jax.config import Config, DataConfig
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    from cusgs_jax.densify.factory import make_strategies
    from cusgs_jax.training import capacity
    from cusgs_jax.training.render import most_work
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.training.step import make_train_step
    from cusgs_jax.types import Camera

    if scene_path == "demo":
        from cusgs_jax.data.demo import demo_scene_path
        scene_path = str(demo_scene_path())
    cfg = Config().replace(features=dict(models=()))
    scene, _ = normalize_scene(load_scene(scene_path, DataConfig(format="colmap", holdout_every=8)))
    cfg = resolve_voxel_size(cfg, scene.points)
    strategies = make_strategies(cfg)
    train_idx = scene.train_indices
    state, tx = init_train_state(cfg, scene.points, len(train_idx), scene.extent, strategies)
    views = [(Camera.of_scene(scene, int(i)), jnp.int32(p)) for p, i in enumerate(train_idx)]
    caps = capacity.Capacities.fitted(most_work(state.anchors, state.nets, views[:8], cfg),
                                      state.anchors.capacity, cfg.model.n_offsets)
    step = make_train_step(cfg, tx, strategies, caps)
    images = scene.images.astype(np.float32) / 255.0

    def batch(k):
        p = k % len(views)
        return dict(image=jnp.asarray(images[train_idx[p]]), camera=views[p][0], index=views[p][1])

    return state, step, batch


def op_names(hlo_text: str) -> dict:
    """{instruction name: its ``op_name`` metadata} of a compiled HLO module's text (JAX's trace path
    of the op: ``jit(step)/transpose(jvp(jit(rasterize)))/while/body/mul`` and the like)."""
    names = {}
    for raw in hlo_text.splitlines():
        m = re.match(r"^\s*(?:ROOT\s+)?%([\w.\-]+)\s*=", raw)
        op = re.search(r'op_name="([^"]+)"', raw)
        if m and op:
            names[m.group(1)] = op.group(1)
    return names


def _where(op_name: str) -> str:
    """A short stage label of an op_name: its path without the leaf op."""
    path = op_name.replace("jit(step)/", "")
    return path.rsplit("/", 1)[0] if "/" in path else path


def main(argv=None):
    import jax

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--top", type=int, default=30)
    parser.add_argument("--features", default=None,
                        help="profile the demo scene's step with these feature models (e.g. demo) instead of RGB only")
    args = parser.parse_args(argv)

    state, step, batch = build_with_features(args.features) if args.features else build(args.scene)
    for k in range(args.warmup):
        state, metrics = step(state, batch(k))
    jax.block_until_ready(metrics)
    b = batch(args.warmup)
    hlo = step.lower(state, b).compile().as_text()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            state, metrics = step(state, b)
            jax.block_until_ready(metrics)
        wall = time.perf_counter() - start
        data = jax.profiler.ProfileData.from_file(glob.glob(os.path.join(folder, "**", "*.xplane.pb"),
                                                            recursive=True)[0])
    table = op_names(hlo)
    by_op, by_line = collections.Counter(), collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            for event in line.events:
                name = event.name
                if name.startswith("ThunkExecutor") or "python" in line.name.lower():
                    continue
                ms = event.duration_ns / 1e6
                by_op[name] += ms
                by_line[_where(table.get(name, "?"))] += ms
    print(json.dumps(dict(scene=args.scene, profiled_step_s=wall, ops_total_ms=sum(by_op.values()),
                          by_trace_path_ms=dict(by_line.most_common(args.top)),
                          top_ops_ms={f"{k} [{table.get(k, '?')}]": v for k, v in by_op.most_common(args.top)}),
                     indent=1))


if __name__ == "__main__":
    main()
