#!/usr/bin/env bash
# Like-for-like scoring of the lens_demo_mask.sh runs: each run baked to a PLY (cusgs-export --refine 0, the same
# for every run) and rendered by cusgs-render-ply at the held-out views of every scene: the pinhole demo (sharp
# ground truth at the demo's own camera, the whole frame) and the lens scenes as the loader gives them with
# data.undistort=mask (scored on their valid pixels). Writes OUT/cross_eval.json.
#   bash experiments/lens_demo_mask_cross.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/lens_demo_mask}
PY=${PY:-.venv/bin/python}
CACHE=${CUSGS_CACHE_DIR:-$HOME/.cache/cusgs_jax}
declare -A SCENE=([pinhole]=$CACHE/demo3-s0-v30-160x120 [opencv]=$CACHE/demo-lens2-opencv-s0-v30-160x120
  [simple_radial]=$CACHE/demo-lens2-simple_radial-s0-v30-160x120)
mkdir -p "$OUT/ply"
echo "{" > "$OUT/cross_eval.json.tmp"
sep=""
for run in pinhole_crop_s0 pinhole_crop_s1 opencv_mask_s0 opencv_mask_s1 simple_radial_mask_s0; do
  PYTHONPATH=src $PY -c "from cusgs_jax.app.export import main; raise SystemExit(main())" "$OUT/$run" \
    "$OUT/ply/$run.ply" --refine 0 --quiet > /dev/null
  for scene in pinhole opencv simple_radial; do
    score=$(PYTHONPATH=src $PY -c "from cusgs_jax.app.render_ply import main; raise SystemExit(main())" \
      "$OUT/ply/$run.ply" --colmap "${SCENE[$scene]}" --undistort mask --quiet 2>/dev/null \
      | $PY -c "import json,sys; d=json.load(sys.stdin); print(json.dumps(dict(psnr=round(d['psnr'],3), ssim=round(d['ssim'],4))))")
    printf '%s "%s on %s": %s' "$sep" "$run" "$scene" "$score" >> "$OUT/cross_eval.json.tmp"
    sep=$',\n'
  done
done
printf '\n}\n' >> "$OUT/cross_eval.json.tmp"
mv "$OUT/cross_eval.json.tmp" "$OUT/cross_eval.json"
