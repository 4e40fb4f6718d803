"""Random starts on object captures: carving and early culling against each other and an older revision (issue 36).

Writes the demo's furniture group as a Blender-layout capture (:mod:`cusgs_jax.data.demo.objects`: RGBA, 70 views
on the upper hemisphere, 10 of them held out; no points → ``data.random_points`` uniform points) and trains it once
per variant, one run at a time:

* ``cull``: the defaults (``data.carve=auto``, ``grow.early_cull=auto`` → on for this random start);
* ``no_cull``: ``grow.early_cull=off`` (carving only);
* ``no_carve_cull`` / ``no_carve``: ``data.carve=none`` with and without early culling (a capture without alpha
  carves almost nothing: this is what early culling alone does);
* ``base``: the same command run by another revision's source (``BASE_SRC=/path/to/worktree/src``), for the
  side-by-side with the revision before carving.

  python experiments/early_cull_objects.py OUT [--seed S] [--size W] [--variants cull,no_cull,...]

Each run goes to OUT/<variant>/; OUT/summary.jsonl gets one row per run: held-out PSNR / SSIM / LPIPS, ``time.total``,
the training clock, and the alive anchors, decoded anchors and active Gaussians at steps 10, 100 and 400
(``metrics.jsonl``, logged every 10 steps).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys

from cusgs_jax.data.demo.objects import generate_object_scenes
from cusgs_jax.run_folder import METRICS_FILE, read_eval

COMMON = ["train.iterations=1500", "features=none", "train.progress=false", "eval.save_renders=false",
          "train.log_every=10", "train.compilation_cache=null"]  # every run compiles its own programs
VARIANTS = {"cull": [], "no_cull": ["grow.early_cull=off"], "no_carve_cull": ["data.carve=none"],
            "no_carve": ["data.carve=none", "grow.early_cull=off"], "base": []}
STEPS = (10, 100, 400)


def run(out: pathlib.Path, scene: pathlib.Path, variant: str) -> dict:
    env = dict(os.environ)
    if variant == "base":
        env["PYTHONPATH"] = os.environ["BASE_SRC"]  # the older revision's package instead of this one
    cmd = [sys.executable, "-m", "cusgs_jax.app.train", *COMMON, f"data.path={scene}", *VARIANTS[variant],
           f"hydra.run.dir={out / variant}"]
    print(" ".join(cmd), flush=True)
    with open(out / f"{variant}.log", "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT, env=env)
    record = read_eval(out / variant)
    rows = {}
    for line in (out / variant / METRICS_FILE).read_text().splitlines():
        row = json.loads(line)
        if row["step"] in STEPS:
            rows[row["step"]] = {k: row[k] for k in ("alive_anchors", "visible_anchors", "active_gaussians")}
    summary = dict(variant=variant, overrides=VARIANTS[variant], psnr=record.psnr, ssim=record.ssim,
                   lpips_vgg=record.get("lpips_vgg"), total_s=(record.time or {}).get("total"),
                   train_wall_s=record.train_wall_s, alive_anchors=record.alive_anchors,
                   carving=record.carving, early_cull=(record.densify or {}).get("early_cull"), at_steps=rows)
    with open(out / "summary.jsonl", "a") as f:
        f.write(json.dumps(summary) + "\n")
    print(json.dumps({k: summary[k] for k in ("variant", "psnr", "ssim", "total_s", "alive_anchors", "at_steps")}),
          flush=True)
    return summary


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--seed", type=int, default=0, help="the capture's cameras (generate_object_scenes)")
    ap.add_argument("--size", type=int, default=128, help="image width = height")
    ap.add_argument("--variants", default="cull,no_cull", help=f"comma-separated, of {', '.join(VARIANTS)}")
    args = ap.parse_args(argv)
    out = args.out.resolve()
    scenes = out / "scenes"
    if not (scenes / "blender" / "transforms_train.json").is_file():
        generate_object_scenes(scenes, seed=args.seed, width=args.size, height=args.size)
    for variant in args.variants.split(","):
        run(out, scenes / "blender", variant)


if __name__ == "__main__":
    main(sys.argv[1:])
