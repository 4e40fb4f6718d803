"""Held-out PSNR of an exported PLY against refinement steps (the curve behind ``cusgs-export``'s default length); prints JSON.

Bakes a finished run once (``cusgs-export --refine 0``, COLMAP frame), then for each
``--steps`` value K refines that bake from scratch for K steps
(:func:`cusgs_jax.io.refine_splats`: a K-step run has its own position-rate decay, as
``cusgs-export --refine K`` would) and scores it on the run's held-out views and on a
few training views (:func:`cusgs_jax.io.heldout_psnr`, as ``cusgs-render-ply`` renders).
K = 0 is the plain bake. Times: wall seconds of each refinement, its first step
(compilation) and the steady seconds per 100 steps; absolute times on a shared machine
are noisy.

    python benchmarks/refine_curve.py RUN_DIR [--steps 0 100 250 500 1000 2000] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import tempfile
import time

import jax
import numpy as np

from cusgs_jax.app.export import _run_scene, export_run
from cusgs_jax.io.load_run import load_trained
from cusgs_jax.config import DataConfig
from cusgs_jax.data.loader import load_scene
from cusgs_jax.io import heldout_psnr, read_ply, refine_splats


def baked_run(run_dir, scene=None):
    """(the trained run, its scene's path, the scene as the run loaded it, the run's plain bake as a
    SplatModel): what a refinement benchmark starts from (``scene``: a path overriding the run's)."""
    model = load_trained(run_dir)
    scene_path = pathlib.Path(scene) if scene else _run_scene(model)[0]
    data, splat = model.cfg.data, model.cfg.splat
    loaded = load_scene(scene_path, DataConfig(format=data.format, downscale=data.downscale,
                                               holdout_every=data.holdout_every, random_points=2),
                        background=splat.background)
    with tempfile.TemporaryDirectory() as tmp:
        bake = export_run(run_dir, pathlib.Path(tmp) / "bake.ply", refine=0, progress=False)
        return model, scene_path, loaded, read_ply(bake["ply"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--steps", type=int, nargs="+", default=[0, 100, 250, 500, 1000, 2000])
    ap.add_argument("--scene", default=None, help="the run's scene (default: its data.path or the demo scene)")
    ap.add_argument("--train-views", type=int, default=8, help="training views scored (evenly spread)")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args()

    model, scene_path, scene, baked = baked_run(args.run_dir, args.scene)
    splat = model.cfg.splat
    train_subset = scene.train_indices[np.unique(np.linspace(0, len(scene.train_indices) - 1,
                                                             args.train_views).round().astype(int))]
    render = dict(background=scene.background, sh_degree=baked.sh_degree, antialiased=bool(splat.antialiased))
    rows = []
    for k in args.steps:
        times = []
        start = time.perf_counter()
        refined = refine_splats(baked, scene, k, l1_weight=model.cfg.loss.l1_weight,
                                ssim_weight=model.cfg.loss.ssim_weight,
                                progress=lambda _: times.append(time.perf_counter()), **render)
        seconds = time.perf_counter() - start
        row = dict(steps=k, psnr_held_out=round(heldout_psnr(refined, scene, **render), 3),
                   psnr_train=round(heldout_psnr(refined, scene, train_subset, **render), 3),
                   seconds=round(seconds, 2))
        if k > 1:
            row.update(first_step_s=round(times[0] - start, 2),
                       steady_s_per_100_steps=round(100 * (times[-1] - times[0]) / (k - 1), 2))
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = dict(run=str(pathlib.Path(args.run_dir).absolute()), scene=str(scene_path), psnr_run=(
        model.evaluation or {}).get("psnr"), gaussians=baked.num_gaussians, sh_degree=baked.sh_degree,
        train_views=int(len(scene.train_indices)), held_out_views=int(len(scene.test_indices)),
        width=scene.width, height=scene.height, curve=rows, device=str(jax.devices()[0]),
        cpu_count=__import__("os").cpu_count(), platform=platform.platform())
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
