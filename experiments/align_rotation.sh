#!/usr/bin/env bash
# data.align: the demo scene and a rotated, scaled, moved copy of it (testing.scenes.transformed_scene), each
# trained with data.align=none and =principal (RGB only, 1500 steps, seed 0). With principal the rotated copy
# normalises to the same frame as the original, so it should train to the same result; with none the voxel grid
# follows the copy's axes.
#   bash experiments/align_rotation.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/align_rotation}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
DEMO=$($PY -c "from cusgs_jax.data.demo import demo_scene_path; print(demo_scene_path())")
ROTATED="$OUT/rotated_scene"
[ -d "$ROTATED" ] || $PY -c "from cusgs_jax.testing.scenes import transformed_scene; transformed_scene('$DEMO', '$ROTATED', scale=3.0, translation=(1.0, 2.0, -4.0), rotation_xyzw=(0.3, -0.5, 0.2, 0.8))"
run() {  # name, scene, align
  $PY -c "from cusgs_jax.app.train import main; main()" data.path="$2" data.align="$3" train.iterations=1500 \
    features=none train.progress=false eval.save_renders=false train.checkpoint_every=0 hydra.run.dir="$OUT/$1" > "$OUT/$1.log" 2>&1
  $PY -c "import json; d=json.load(open('$OUT/$1/eval.json')); print(json.dumps(dict(run='$1', psnr=d['psnr'], ssim=d['ssim'], alive_anchors=d['alive_anchors'])))"
}
for align in ${ALIGNS:-principal none}; do
  for scene in ${SCENES:-original rotated}; do
    path=$DEMO; [ "$scene" = rotated ] && path=$ROTATED
    run "${scene}_${align}" "$path" "$align"
  done
done
