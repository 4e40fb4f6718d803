#!/usr/bin/env bash
# Like-for-like scoring of the lens_demo_mask.sh runs (lens_demo_cross.sh with these runs): each run baked to a PLY
# (cusgs-export --refine 0, the same for every run) and rendered by cusgs-render-ply at the held-out views of every
# scene: the pinhole demo (sharp ground truth at the demo's own camera, the whole frame) and the lens scenes as the
# loader gives them with data.undistort=mask (scored on their valid pixels). Writes OUT/cross_eval.json.
#   bash experiments/lens_demo_mask_cross.sh [OUT]
set -euo pipefail
RUNS="pinhole_crop_s0 pinhole_crop_s1 opencv_mask_s0 opencv_mask_s1 simple_radial_mask_s0" \
  SCENES="pinhole opencv simple_radial" UNDISTORT=mask \
  exec bash "$(dirname "$0")/lens_demo_cross.sh" "${1:-experiments/results/lens_demo_mask}"
