#!/usr/bin/env bash
# Like-for-like scoring of the lens_demo_lens.sh runs (lens_demo_cross.sh with these runs): each run baked to a PLY
# (cusgs-export --refine 0, the same for every run) and rendered by cusgs-render-ply --undistort lens at the held-out
# views of every scene: the pinhole demo (sharp, its own pinhole camera, the whole frame) and the lens scenes as
# captured, drawn through their lens (the whole frame). Writes OUT/cross_eval.json.
#   bash experiments/lens_demo_lens_cross.sh [OUT]
set -euo pipefail
RUNS="pinhole_crop_s0 pinhole_crop_s1 opencv_lens_s0 opencv_lens_s1 simple_radial_lens_s0 simple_radial_lens_s1" \
  SCENES="pinhole opencv simple_radial" UNDISTORT=lens \
  exec bash "$(dirname "$0")/lens_demo_cross.sh" "${1:-experiments/results/lens_demo_lens}"
