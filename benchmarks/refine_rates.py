"""Held-out and training-view PSNR of an export refined with other learning rates (chose ``RefineSettings``' rates); prints JSON lines.

Bakes a finished run once (``cusgs-export --refine 0``, COLMAP frame), then refines that bake
for ``--steps`` steps once per variant (a JSON object ``{name: {RefineSettings field: value}}``;
``{}`` keeps the defaults) and prints, per variant: the held-out PSNR, the PSNR on 8 evenly
spread training views, the mean training loss of each pass over the training views
(``epoch_loss``) and the wall seconds. benchmarks/results/refine/rates_1000_steps.json holds
the rows measured with it.

    python benchmarks/refine_rates.py RUN_DIR --steps 1000 \\
        --variants '{"default": {}, "x2": {"lr_sh_dc": 2e-2, "lr_sh_rest": 1e-3, "lr_scaling": 4e-2, "lr_rotation": 8e-3}}'
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import pathlib
import time

import numpy as np

from cusgs_jax.io import heldout_psnr, refine_splats

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from refine_curve import baked_run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--variants", default='{"default": {}}', help="JSON {name: {RefineSettings field: value}}")
    ap.add_argument("--scene", default=None, help="the run's scene (default: its data.path or the demo scene)")
    args = ap.parse_args()

    variants = json.loads(args.variants)
    model, scene_path, scene, baked = baked_run(args.run_dir, args.scene)
    splat = model.cfg.splat
    train = scene.train_indices
    subset = train[np.unique(np.linspace(0, len(train) - 1, 8).round().astype(int))]
    render = dict(background=scene.background, sh_degree=baked.sh_degree, antialiased=bool(splat.antialiased))
    print(json.dumps(dict(run=str(pathlib.Path(args.run_dir).absolute()), scene=str(scene_path),
                          psnr_run=(model.evaluation or {}).get("psnr"), psnr_bake=heldout_psnr(baked, scene, **render),
                          train_views=len(train), held_out_views=len(scene.test_indices))), flush=True)
    for name, overrides in variants.items():
        history: list = []
        start = time.perf_counter()
        refined = refine_splats(baked, scene, args.steps, l1_weight=model.cfg.loss.l1_weight,
                                ssim_weight=model.cfg.loss.ssim_weight, history=history, **render, **overrides)
        seconds = time.perf_counter() - start
        loss = np.array([h["loss"] for h in history])
        epochs = loss[:len(loss) // len(train) * len(train)].reshape(-1, len(train)).mean(axis=1)
        print(json.dumps(dict(name=name, overrides=overrides, steps=args.steps,
                              held=round(heldout_psnr(refined, scene, **render), 3),
                              train=round(heldout_psnr(refined, scene, subset, **render), 3),
                              epoch_loss=[round(float(x), 5) for x in epochs], sec=round(seconds, 1))), flush=True)


if __name__ == "__main__":
    main()
