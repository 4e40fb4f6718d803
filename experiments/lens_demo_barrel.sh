#!/usr/bin/env bash
# Control for the lens runs' like-for-like deficit (experiments/README.md): is it the lenses' narrower views? The
# demo's lenses are pincushion (k = +0.09: each view sees less of the room than the pinhole's). This one is barrel
# (SIMPLE_RADIAL k = -0.09, same focal length: each view sees more). Same settings as lens_demo_lens.sh (seed 0),
# then the baked PLYs of this run and of lens_demo_lens.sh's pinhole run scored on this scene through its lens and
# on the pinhole demo. Appends to OUT/summary.jsonl and writes OUT/barrel_cross.json.
#   bash experiments/lens_demo_barrel.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/lens_demo_lens}
PY=${PY:-.venv/bin/python}
CACHE=${CUSGS_CACHE_DIR:-$HOME/.cache/cusgs_jax}
SCENE=$OUT/control/barrel
if [ ! -f "$SCENE/scene.json" ]; then
  PYTHONPATH=src $PY -c "from cusgs_jax.data.demo.lens import write_lens_demo as w; w('$SCENE', 'SIMPLE_RADIAL', [128.0, 80.0, 60.0, -0.09], lens_name='barrel')"
fi
name=barrel_lens_s0
PYTHONPATH=src $PY -c "from cusgs_jax.app.train import main; main()" data.path="$SCENE" data.undistort=lens \
  train.seed=0 train.iterations=1500 features=none train.progress=false eval.save_renders=false \
  hydra.run.dir="$OUT/$name" > "$OUT/$name.log" 2>&1
$PY -c "import json; d=json.load(open('$OUT/$name/eval.json')); print(json.dumps(dict(run='$name', psnr=d['psnr'], ssim=d['ssim'], valid_pixels=d['valid_pixels'], size=[d['width'], d['height']], per_view=[round(v['psnr'], 3) for v in d['per_view']], train_wall_s=d['train_wall_s'], alive_anchors=d['alive_anchors'])))" >> "$OUT/summary.jsonl"
PYTHONPATH=src $PY -c "from cusgs_jax.app.export import main; raise SystemExit(main())" "$OUT/$name" \
  "$OUT/ply/$name.ply" --refine 0 --quiet > /dev/null
echo "{" > "$OUT/barrel_cross.json.tmp"
sep=""
for run in pinhole_crop_s0 pinhole_crop_s1 $name; do
  for scene in "$CACHE/demo3-s0-v30-160x120" "$SCENE"; do
    score=$(PYTHONPATH=src $PY -c "from cusgs_jax.app.render_ply import main; raise SystemExit(main())" \
      "$OUT/ply/$run.ply" --colmap "$scene" --undistort lens --quiet 2>/dev/null \
      | $PY -c "import json,sys; d=json.load(sys.stdin); print(json.dumps(dict(psnr=round(d['psnr'],3), ssim=round(d['ssim'],4))))")
    printf '%s "%s on %s": %s' "$sep" "$run" "$(basename "$scene")" "$score" >> "$OUT/barrel_cross.json.tmp"
    sep=$',\n'
  done
done
printf '\n}\n' >> "$OUT/barrel_cross.json.tmp"
mv "$OUT/barrel_cross.json.tmp" "$OUT/barrel_cross.json"
