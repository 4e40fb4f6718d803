#!/usr/bin/env bash
# Issue 21, data.undistort=lens: the demo room through the OPENCV and SIMPLE_RADIAL lenses, trained on the images as
# captured and rasterised through the lens model itself (no undistortion), against the pinhole demo, same settings (RGB
# only, 1500 steps), one run after another, two seeds each for the run-to-run spread.
#   bash experiments/lens_demo_lens.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/lens_demo_lens}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
run() {  # lens, undistort mode, seed
  local name=$1_$2_s$3
  PYTHONPATH=src $PY -c "from cusgs_jax.app.train import main; main()" data.demo.lens=$1 data.undistort=$2 \
    train.seed=$3 train.iterations=1500 features=none train.progress=false eval.save_renders=false \
    hydra.run.dir="$OUT/$name" > "$OUT/$name.log" 2>&1
  $PY -c "import json; d=json.load(open('$OUT/$name/eval.json')); print(json.dumps(dict(run='$name', psnr=d['psnr'], ssim=d['ssim'], valid_pixels=d['valid_pixels'], size=[d['width'], d['height']], per_view=[round(v['psnr'], 3) for v in d['per_view']], train_wall_s=d['train_wall_s'], alive_anchors=d['alive_anchors'])))" >> "$OUT/summary.jsonl"
}
for spec in "opencv lens 0" "simple_radial lens 0" "pinhole crop 0" "opencv lens 1" "simple_radial lens 1" "pinhole crop 1"; do
  run $spec
done
