#!/usr/bin/env bash
# Like-for-like scoring of the lens_demo.sh runs: each run baked to a PLY (cusgs-export --refine 0, the same for
# every run) and rendered by cusgs-render-ply at the held-out views of every scene: the pinhole demo, the lens
# scenes as the loader gives them (undistorted) and the sharp pinhole controls at the lens scenes' cameras
# (lens_demo_control.py). Run after lens_demo.sh and lens_demo_control.py; writes OUT/cross_eval.json.
#   bash experiments/lens_demo_cross.sh [OUT]
# RUNS, SCENES and UNDISTORT (cusgs-render-ply --undistort) pick other runs, scenes and undistortion
# (lens_demo_mask_cross.sh sets them).
set -euo pipefail
OUT=${1:-experiments/results/lens_demo}
PY=${PY:-.venv/bin/python}
CACHE=${CUSGS_CACHE_DIR:-$HOME/.cache/cusgs_jax}
declare -A SCENE=([pinhole]=$CACHE/demo3-s0-v30-160x120 [opencv]=$CACHE/demo-lens4-opencv-s0-v30-160x120
  [simple_radial]=$CACHE/demo-lens4-simple_radial-s0-v30-160x120 [sharp_opencv]=$OUT/control/sharp_opencv
  [sharp_simple_radial]=$OUT/control/sharp_simple_radial)
mkdir -p "$OUT/ply"
echo "{" > "$OUT/cross_eval.json.tmp"
sep=""
RUNS=${RUNS:-pinhole_s0 opencv_s0 simple_radial_s0 sharp_opencv}
SCENES=${SCENES:-pinhole opencv sharp_opencv simple_radial sharp_simple_radial}
UNDISTORT=${UNDISTORT:-crop}
for run in $RUNS; do
  PYTHONPATH=src $PY -c "from cusgs_jax.app.export import main; raise SystemExit(main())" "$OUT/$run" \
    "$OUT/ply/$run.ply" --refine 0 --quiet > /dev/null
  for scene in $SCENES; do
    score=$(PYTHONPATH=src $PY -c "from cusgs_jax.app.render_ply import main; raise SystemExit(main())" \
      "$OUT/ply/$run.ply" --colmap "${SCENE[$scene]}" --undistort "$UNDISTORT" --quiet 2>/dev/null \
      | $PY -c "import json,sys; d=json.load(sys.stdin); print(json.dumps(dict(psnr=round(d['psnr'],3), ssim=round(d['ssim'],4))))")
    printf '%s "%s on %s": %s' "$sep" "$run" "$scene" "$score" >> "$OUT/cross_eval.json.tmp"
    sep=$',\n'
  done
done
printf '\n}\n' >> "$OUT/cross_eval.json.tmp"
mv "$OUT/cross_eval.json.tmp" "$OUT/cross_eval.json"
