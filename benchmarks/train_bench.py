"""Train-step speed on the demo scene at 1×, 2× and 4× its pixels; prints JSON.

For each resolution: compile time of the jitted step and the median step time
over ``--steps`` steps (after compilation), with the anchor count used; with
``--features`` also the same step with the demo feature field
(``config.DEMO_FEATURE_MODELS``: daisy + semantic + vgg16, less vgg16 without the lpips extra); with
``--feature-sets daisy,semantic daisy,semantic,vgg16`` the step with each listed
set of the demo's feature models instead (their settings from
``config.DEMO_FEATURE_MODELS``). All variants of one resolution live in one
process and their steps are timed interleaved (variant 1 step i, variant 2
step i, …), so CPU contention from other work affects them alike; each row has
``ratio``, its median step time over the first variant's. Rows with features
also give each model's PSC bank size and extraction time per view.

    python benchmarks/train_bench.py [--steps 20] [--views 12] [--features]
    python benchmarks/train_bench.py --steps 5 --pixel-factors 1 --feature-sets none daisy,semantic daisy,semantic,vgg16
    python benchmarks/train_bench.py --backends jax pallas     # each variant with each compositor (a GPU)

With ``--backends`` every feature set runs once per compositor (``splat.backend``), interleaved too.
``--target`` times scale_bench.py's target scene instead (60 views at 640×480, ~100k SfM points:
``--views 60 --pixel-factors 16 --points 103000``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import DEMO_FEATURE_MODELS, Config, DataConfig
from cusgs_jax.training.inputs import load_feature_targets
from cusgs_jax.data.loader import load_scene
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.normalize import normalize_scene
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.extract import extract_scene
from cusgs_jax.extract.optional import available_models
from cusgs_jax.app.resolve import resolve_voxel_size
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def feature_set(spec: str) -> tuple:
    """"none" → (); "daisy,semantic" → those demo models (DEMO_FEATURE_MODELS' settings), in that order."""
    if spec == "none":
        return ()
    known = {m.name: m for m in DEMO_FEATURE_MODELS}
    names = spec.split(",")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SystemExit(f"--feature-sets: unknown model(s) {unknown}; the demo's are {sorted(known)}")
    return tuple(known[n] for n in names)


def setup(scene_path: str, voxel_size, models: tuple, backend: str = "auto"):
    """(step, state, batch(i) -> batch dict, info) of one variant on the scene at ``scene_path``."""
    cfg = Config().replace(train=dict(iterations=30_000), model=dict(voxel_size=voxel_size),
                           features=dict(models=models), splat=dict(backend=backend))
    scene, _ = normalize_scene(load_scene(scene_path, DataConfig(format="colmap", holdout_every=0)))
    cfg = resolve_voxel_size(cfg, scene.points)
    banks, targets, info = None, {}, {}
    if models:
        # every view as cusgs-extract loads it (its initial points are not needed: 2 random ones, never carved)
        described = load_scene(scene_path, DataConfig(holdout_every=0, random_points=2, carve="none"))
        for m in models:  # extract here (not in load_feature_targets) to time it
            summary = extract_scene(described, m.name, overwrite=True, progress=False)
            info[m.name] = dict(dim=summary.dim, resolution=list(summary.resolution),
                                extract_ms_per_view=1000 * summary.seconds_per_view)
        maps, banks = load_feature_targets(cfg.features, scene, 0)
        for name, bank in banks.items():
            info[name]["bank_entries"] = int(bank.shape[0])
        banks = {k: jnp.asarray(v) for k, v in banks.items()}
        targets = {k: jnp.asarray(fs.maps.astype(np.float16)) for k, fs in maps.items()}
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, scene.points, len(scene.names), scene.extent, strategies, banks)
    step = make_train_step(cfg, tx, strategies)
    images = jnp.asarray(scene.images.astype(np.float32) / 255.0)

    def batch(i):
        v = i % len(scene.names)
        b = dict(image=images[v], camera=Camera.of_scene(scene, v), index=jnp.int32(v))
        if models:
            b["features"] = {k: t[v] for k, t in targets.items()}
            b["banks"] = banks
        return b

    return step, state, batch, info


def bench(width: int, height: int, steps: int, views: int, voxel_size, variants: list[tuple],
          points: int = 6000) -> list[dict]:
    """One row per (feature-model set, compositor) in ``variants``, steps timed interleaved."""
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        path = generate_demo_scene(os.path.join(tmp, "demo"), num_views=views, width=width, height=height,
                                   num_points=points)
        for models, backend in variants:
            step, state, batch, info = setup(path, voxel_size, models, backend)
            start = time.perf_counter()
            try:
                state, metrics = step(state, batch(0))
                jax.block_until_ready(metrics)
            except Exception as error:  # noqa: BLE001 — one failing variant must not hide the others
                print(json.dumps(dict(backend=backend, width=width, height=height,
                                      error=f"{type(error).__name__}: {str(error)[:2000]}")), file=sys.stderr,
                      flush=True)
                continue
            runs.append(dict(step=step, state=state, batch=batch, info=info, models=models, backend=backend,
                             compile_s=time.perf_counter() - start, times=[]))
    for i in range(1, steps + 1):
        for run in runs:
            start = time.perf_counter()
            run["state"], metrics = run["step"](run["state"], run["batch"](i))
            jax.block_until_ready(metrics)
            run["times"].append(time.perf_counter() - start)
    first = float(np.median(runs[0]["times"]))
    rows = []
    for run in runs:
        state, median = run["state"], float(np.median(run["times"]))
        rows.append(dict(features=bool(run["models"]), models=[m.name for m in run["models"]], backend=run["backend"],
                         query_dim=sum(m.query_dim for m in run["models"]), width=width, height=height,
                         pixels=width * height, anchors=int(np.sum(state.anchors.alive)),
                         capacity=state.anchors.capacity, compile_s=run["compile_s"], median_step_s=median,
                         ratio=median / first, steps=steps, feature_models=run["info"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--voxel-size", type=lambda v: None if v == "auto" else float(v), default=None,
                        help="in units of the scene extent, or auto")
    parser.add_argument("--features", action="store_true", help="also time the step with the demo feature field")
    parser.add_argument("--feature-sets", nargs="+", default=None, metavar="MODELS",
                        help="time these sets of the demo's feature models instead (comma-separated names, "
                             "or none), e.g. none daisy,semantic daisy,semantic,vgg16")
    parser.add_argument("--backends", nargs="+", default=["auto"], choices=["auto", "jax", "pallas"],
                        help="compositors (splat.backend) to time each variant with")
    parser.add_argument("--points", type=int, default=6000, help="SfM points the demo generator is asked for")
    parser.add_argument("--target", action="store_true",
                        help="scale_bench.py's target scene: 60 views, 640x480, 103000 points asked for")
    parser.add_argument("--pixel-factors", type=int, nargs="+", default=[1, 2, 4],
                        help="image sizes: 160x120 times these pixel factors")
    args = parser.parse_args(argv)
    if args.target:
        args.views, args.pixel_factors, args.points = 60, [16], 103_000
    if args.feature_sets:
        variants = [feature_set(spec) for spec in args.feature_sets]
    else:
        variants = [()] + ([available_models(DEMO_FEATURE_MODELS)] if args.features else [])
    variants = [(models, backend) for models in variants for backend in args.backends]
    rows = []
    for factor in args.pixel_factors:
        scale = math.sqrt(factor)
        width, height = int(round(160 * scale / 2) * 2), int(round(120 * scale / 2) * 2)
        for row in bench(width, height, args.steps, args.views, args.voxel_size, variants, args.points):
            rows.append(dict(pixel_factor=factor, **row))
            print(json.dumps(rows[-1]), flush=True, file=sys.stderr)
    print(json.dumps(dict(benchmark="train_step", jax=jax.__version__, backend=jax.default_backend(),
                          cpu_count=os.cpu_count(), machine=platform.machine(), results=rows), indent=1))


if __name__ == "__main__":
    main()
