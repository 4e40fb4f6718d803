#!/usr/bin/env bash
# Issue 21, data.undistort=lens: the demo room through the OPENCV and SIMPLE_RADIAL lenses, trained on the images as
# captured and rasterised through the lens model itself (no undistortion), against the pinhole demo, same settings (RGB
# only, 1500 steps), one run after another, two seeds each for the run-to-run spread (lens_demo_mask.sh's runs).
#   bash experiments/lens_demo_lens.sh [OUT]
set -euo pipefail
SPECS="opencv lens 0;simple_radial lens 0;pinhole crop 0;opencv lens 1;simple_radial lens 1;pinhole crop 1" \
  exec bash "$(dirname "$0")/lens_demo_mask.sh" "${1:-experiments/results/lens_demo_lens}"
