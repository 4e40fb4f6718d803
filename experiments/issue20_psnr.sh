#!/usr/bin/env bash
# Held-out PSNR and wall time of the revision before issue 20 (OLD_SRC) beside today's step, sparse and dense,
# on the demo scene: RGB only, 1500 steps, runs alternating one after another on the same machine.
#   OLD_SRC=<worktree of e908d45>/src bash experiments/issue20_psnr.sh [OUT]
set -euo pipefail
OUT=${1:-experiments/results/issue20_psnr}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
run() {  # name, PYTHONPATH, overrides...
  local name=$1 src=$2; shift 2
  PYTHONPATH=$src $PY -c "from cusgs_jax.app.train import main; main()" train.iterations=1500 features=none \
    train.progress=false eval.save_renders=false hydra.run.dir="$OUT/$name" "$@" > "$OUT/$name.log" 2>&1
  $PY -c "import json,sys; d=json.load(open('$OUT/$name/eval.json')); print(json.dumps(dict(run='$name', psnr=d['psnr'], ssim=d['ssim'], train_wall_s=d['train_wall_s'], render_ms_per_view=d['render_ms_per_view'], alive_anchors=d['alive_anchors'])))"
}
for seed in 0 1; do
  run old_s$seed "$OLD_SRC" train.seed=$seed
  run sparse_s$seed src train.seed=$seed
  run dense_s$seed src train.seed=$seed optim.sparse=false
done
