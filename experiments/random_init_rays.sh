#!/usr/bin/env bash
# data.random_init=cube against cube_and_rays (issue 21), both scenes without points, one run at a time:
# the demo room in the Blender layout (experiments/random_init_blender.py; its walls lie outside the cube)
# and the demo objects in the Blender layout (experiments/random_init_objects.py; object-centric, on white).
# Every run: 1500 steps, features=none, default 100k random points, train.seed=0.
#   bash experiments/random_init_rays.sh [OUT]      (OUT defaults to experiments/results/random_init_rays)
# ROOM_INITS / OBJECT_INITS (space-separated) choose which runs; SEED sets train.seed (it also seeds the random
# points) and suffixes the run names with _s$SEED; summary.jsonl collects the eval.json rows.
set -euo pipefail
OUT=$(realpath -m "${1:-experiments/results/random_init_rays}")
mkdir -p "$OUT/scenes"
[ -f "$OUT/scenes/room/transforms_train.json" ] || python experiments/random_init_blender.py "$OUT/scenes/room"
[ -f "$OUT/scenes/objects/blender/scene.json" ] || python -c \
  "import sys; from cusgs_jax.data.demo.objects import generate_object_scenes as g; g(sys.argv[1])" "$OUT/scenes/objects"
SEED_ARGS=(); TAG=""
if [ -n "${SEED-}" ]; then SEED_ARGS=("train.seed=$SEED"); TAG="_s$SEED"; fi
run() {  # name, then overrides
  local name=$1$TAG; shift
  python -m cusgs_jax.app.train train.iterations=1500 features=none train.progress=false eval.save_renders=false \
    "${SEED_ARGS[@]}" "$@" hydra.run.dir="$OUT/$name" > "$OUT/$name.log" 2>&1
  python - "$OUT" "$name" <<'PY'
import json, pathlib, sys
out, name = pathlib.Path(sys.argv[1]), sys.argv[2]
d = json.loads((out / name / "eval.json").read_text())
row = {"run": name, **{k: d.get(k) for k in ("psnr", "ssim", "lpips_vgg", "alive_anchors", "voxel_size",
                                               "train_wall_s", "evaluated_on")}}
print(json.dumps(row))
with open(out / "summary.jsonl", "a") as f:
    f.write(json.dumps(row) + "\n")
PY
}
for init in ${ROOM_INITS-cube_and_rays cube}; do
  run "room_$init" data.path="$OUT/scenes/room" splat.background=[0,0,0] data.random_init="$init"
done
for init in ${OBJECT_INITS-cube_and_rays cube}; do
  run "objects_$init" data.path="$OUT/scenes/objects/blender" data.random_init="$init"
done
# the same room in the nerfstudio layout without a PLY, all defaults (data.random_init=auto → cube_and_rays)
if [ -n "${NERFSTUDIO-}" ]; then
  [ -f "$OUT/scenes/room_ns/transforms.json" ] || python experiments/random_init_nerfstudio.py "$OUT/scenes/room_ns"
  run room_nerfstudio_auto data.path="$OUT/scenes/room_ns"
fi
