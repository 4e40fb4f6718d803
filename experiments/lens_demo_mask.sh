#!/usr/bin/env bash
# Issue 21, data.undistort=mask: the demo room through the OPENCV and SIMPLE_RADIAL lenses, undistorted to the
# source frame with a valid-pixel mask (instead of cropped), against the pinhole demo, same settings (RGB only,
# 1500 steps), one run after another; a second seed of pinhole and OPENCV for the run-to-run spread.
#   bash experiments/lens_demo_mask.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/lens_demo_mask}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
run() {  # lens, undistort mode, seed
  local name=$1_$2_s$3
  PYTHONPATH=src $PY -c "from cusgs_jax.app.train import main; main()" data.demo.lens=$1 data.undistort=$2 \
    train.seed=$3 train.iterations=1500 features=none train.progress=false eval.save_renders=false \
    hydra.run.dir="$OUT/$name" > "$OUT/$name.log" 2>&1
  $PY -c "import json; d=json.load(open('$OUT/$name/eval.json')); print(json.dumps(dict(run='$name', psnr=d['psnr'], ssim=d['ssim'], valid_pixels=d['valid_pixels'], size=[d['width'], d['height']], per_view=[round(v['psnr'], 3) for v in d['per_view']], train_wall_s=d['train_wall_s'], alive_anchors=d['alive_anchors'])))" >> "$OUT/summary.jsonl"
}
# SPECS: "lens mode seed" triples, one run each (lens_demo_lens.sh sets its own)
SPECS=${SPECS:-"opencv mask 0;simple_radial mask 0;pinhole crop 0;opencv mask 1;pinhole crop 1"}
IFS=';' read -ra SPEC_LIST <<< "$SPECS"
for spec in "${SPEC_LIST[@]}"; do
  run $spec
done
