#!/usr/bin/env bash
# Issue 21: the demo room through a pinhole, an OPENCV and a SIMPLE_RADIAL lens (data.demo.lens, data/demo/lens.py),
# trained with identical settings (RGB only, 1500 steps: what CPU time allows), one run after another.
# The distorted scenes are generated into the cache and undistorted on load: no manual step.
#   bash experiments/lens_demo.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/lens_demo}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
run() {  # lens, seed
  local name=$1_s$2
  PYTHONPATH=src $PY -c "from cusgs_jax.app.train import main; main()" data.demo.lens=$1 data.undistort=crop train.seed=$2 \
    train.iterations=1500 features=none train.progress=false eval.save_renders=false hydra.run.dir="$OUT/$name" \
    > "$OUT/$name.log" 2>&1
  $PY -c "import json; d=json.load(open('$OUT/$name/eval.json')); print(json.dumps(dict(run='$name', psnr=d['psnr'], ssim=d['ssim'], per_view=[round(v['psnr'], 3) for v in d['per_view']], train_wall_s=d['train_wall_s'], alive_anchors=d['alive_anchors'])))" >> "$OUT/summary.jsonl"
}
for spec in "pinhole 0" "opencv 0" "simple_radial 0" "pinhole 1"; do
  run $spec
done
# the control: sharp pinhole images at the OPENCV scene's undistorted camera (same size, poses, points)
PYTHONPATH=src $PY experiments/lens_demo_control.py "$OUT/control"
PYTHONPATH=src $PY -c "from cusgs_jax.app.train import main; main()" data.path="$OUT/control/sharp_opencv" train.seed=0 \
  train.iterations=1500 features=none train.progress=false eval.save_renders=false hydra.run.dir="$OUT/sharp_opencv" \
  > "$OUT/sharp_opencv.log" 2>&1
