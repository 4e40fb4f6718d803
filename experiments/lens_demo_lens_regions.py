"""Where the lens-trained models lose against the pinhole-trained ones on the lens scenes' own views.

Each baked PLY of ``lens_demo_lens_cross.sh`` (``results/lens_demo_lens/ply/``) is rendered through the lens at
the held-out views of the OPENCV and SIMPLE_RADIAL demo scenes (``data.undistort=lens``, as
``cusgs-render-ply --undistort lens``), and the squared error is binned by the pixel's distance from the
principal point (inner / middle / outer third of the largest distance). Prints JSON, one row per (model, scene).

    PYTHONPATH=src python experiments/lens_demo_lens_regions.py [RESULTS]
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo.lens import lens_demo_path
from cusgs_jax.data.loader import load_scene
from cusgs_jax.io import read_ply, recentre_splats, render_splats_exact, scene_camera

RESULTS = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "experiments/results/lens_demo_lens")
MODELS = ["pinhole_crop_s0", "pinhole_crop_s1", "opencv_lens_s0", "opencv_lens_s1", "simple_radial_lens_s0",
          "simple_radial_lens_s1"]


def main():
    for lens in ("opencv", "simple_radial"):
        scene = load_scene(lens_demo_path(lens=lens), DataConfig(undistort="lens"))
        K = scene.Ks[0]
        jj, ii = np.meshgrid(np.arange(scene.width) + 0.5, np.arange(scene.height) + 0.5)
        radius = np.hypot(jj - K[0, 2], ii - K[1, 2])
        bins = np.minimum((3 * radius / radius.max()).astype(int), 2)
        for name in MODELS:
            model, shift = recentre_splats(read_ply(RESULTS / "ply" / f"{name}.ply"),
                                           scene.camera_centers.mean(axis=0))
            errors = np.zeros(3)
            counts = np.zeros(3)
            for view in scene.test_indices:
                out, _ = render_splats_exact(model, scene_camera(scene, int(view), shift), background=scene.background)
                image = np.clip(np.asarray(out.image, np.float64), 0, 1)
                sq = np.mean((image - scene.images[view] / 255.0) ** 2, axis=-1)
                for b in range(3):
                    errors[b] += sq[bins == b].sum()
                    counts[b] += (bins == b).sum()
            psnr = -10 * np.log10(errors / counts)
            print(json.dumps(dict(model=name, scene=lens, psnr_inner=round(psnr[0], 3), psnr_middle=round(psnr[1], 3),
                                  psnr_outer=round(psnr[2], 3),
                                  pixel_share=[round(c / counts.sum(), 3) for c in counts])), flush=True)


if __name__ == "__main__":
    main()
