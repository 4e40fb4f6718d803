"""Random initial points vs SfM points on an object-centric capture (issue 21).

Writes the demo's furniture group without the room (:mod:`cusgs_jax.data.demo.objects`: RGBA, no
walls or floor, 70 views on the upper hemisphere, 128×128) twice from the same renders — Blender
layout (60 train / 10 test, no points → ``data.random_points`` uniform points) and COLMAP layout
(the same images on white, SfM-style surface points; ``data.holdout_every=7`` holds out the same 10
views) — then trains each with the same settings, one run at a time, and writes a summary.

  python experiments/random_init_objects.py [OUT] [extra overrides for the Blender run ...]

OUT defaults to experiments/results/random_init_objects; runs go to OUT/<name><TAG>/ (eval.json kept).
Environment: RUNS=colmap,blender (which runs), TAG (suffix of the run names), SEED (train.seed of both runs).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

from cusgs_jax.data.demo.objects import generate_object_scenes
from cusgs_jax.run_folder import read_eval

COMMON = ["train.iterations=1500", "features=none", "train.progress=false", "eval.save_renders=false"]


def run(out: pathlib.Path, name: str, overrides: list[str]) -> dict:
    cmd = [sys.executable, "-m", "cusgs_jax.app.train", *COMMON, *overrides, f"hydra.run.dir={out / name}"]
    print(" ".join(cmd), flush=True)
    with open(out / f"{name}.log", "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT, env=os.environ)
    d = read_eval(out / name).to_json()  # the run-folder contract (cusgs_jax/run_folder.py)
    row = dict(run=name, overrides=overrides, psnr=d["psnr"], ssim=d["ssim"], lpips_vgg=d.get("lpips_vgg"),
               lpips_alex=d.get("lpips_alex"), alive_anchors=d.get("alive_anchors"),
               voxel_size=d.get("voxel_size"), train_wall_s=d.get("train_wall_s"),
               evaluated_on=d.get("evaluated_on"), test_views=[v["name"] for v in d.get("per_view", [])])
    with open(out / "summary.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps({k: row[k] for k in ("run", "psnr", "ssim", "lpips_vgg", "alive_anchors", "train_wall_s")}))
    return row


def main(argv: list[str]) -> None:
    out = pathlib.Path(argv[0] if argv else "experiments/results/random_init_objects").resolve()
    which = os.environ.get("RUNS", "colmap,blender").split(",")
    extra = argv[1:]
    scenes = out / "scenes"
    if not (scenes / "blender" / "scene.json").is_file():
        generate_object_scenes(scenes)
    out.mkdir(parents=True, exist_ok=True)
    tag = os.environ.get("TAG", "")
    seed = os.environ.get("SEED")  # train.seed for both runs (it also seeds the random points)
    both = [f"train.seed={seed}"] if seed else []
    if "colmap" in which:
        run(out, f"colmap_sfm{tag}", [f"data.path={scenes / 'colmap'}", "data.holdout_every=7",
                                      "splat.background=[1,1,1]", *both])
    if "blender" in which:
        run(out, f"blender_random{tag}", [f"data.path={scenes / 'blender'}", *both, *extra])


if __name__ == "__main__":
    main(sys.argv[1:])
