"""How far the first-order lens projection (splat/lens.py) is from drawing the same Gaussians exactly.

A trained model (a baked PLY of ``lens_demo_lens_cross.sh``) is drawn at the held-out views of a lens demo scene
two ways: (1) through the lens by the rasteriser (EWA with the lens's Jacobian — what ``data.undistort=lens``
trains and scores with); (2) exactly, up to resampling: drawn by the pinhole rasteriser at ``--factor``× the
resolution over the lens's field of view, then looked up at every distorted pixel centre's undistorted direction
(COLMAP's ``cam_from_img``) with bilinear interpolation. The low-pass filter is matched (eps2d·factor² in the
fine render). Prints the PSNR between (1) and (2) per view and overall, and each one's PSNR against the images.

    PYTHONPATH=src python experiments/lens_approximation.py [PLY] [--lens opencv] [--factor 4] [--scene FOLDER]
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax.numpy as jnp
import numpy as np
import pycolmap

from cusgs_jax.config import DataConfig
from cusgs_jax.data.demo.lens import lens_demo_path
from cusgs_jax.data.loader import load_scene
from cusgs_jax.io import read_ply, recentre_splats, render_splats_exact, scene_camera
from cusgs_jax.types import Camera


def _psnr(a, b):
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


def _bilinear(image, x, y):
    """image [H, W, C] sampled at continuous pixel coordinates (pixel centres at +0.5)."""
    x, y = x - 0.5, y - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    h, w = image.shape[:2]

    def at(yy, xx):
        return image[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)]

    return ((1 - fx) * (1 - fy) * at(y0, x0) + fx * (1 - fy) * at(y0, x0 + 1) + (1 - fx) * fy * at(y0 + 1, x0)
            + fx * fy * at(y0 + 1, x0 + 1))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ply", nargs="?", default="experiments/results/lens_demo_lens/ply/pinhole_crop_s0.ply")
    parser.add_argument("--lens", default="opencv")
    parser.add_argument("--factor", type=int, default=4)
    parser.add_argument("--scene", default=None, help="a lens demo folder (write_lens_demo) instead of --lens's")
    args = parser.parse_args()
    path = lens_demo_path(lens=args.lens) if args.scene is None else pathlib.Path(args.scene)
    scene = load_scene(path, DataConfig(undistort="lens"))
    camera = pycolmap.Reconstruction(str(path / "sparse" / "0")).cameras[1]
    model, shift = recentre_splats(read_ply(args.ply), scene.camera_centers.mean(axis=0))
    jj, ii = np.meshgrid(np.arange(scene.width) + 0.5, np.arange(scene.height) + 0.5)
    directions = camera.cam_from_img(np.stack([jj.ravel(), ii.ravel()], -1))  # [H·W, 2] undistorted (u, v)
    lo, hi = directions.min(0) - 0.02, directions.max(0) + 0.02
    f = args.factor * max(scene.Ks[0][0, 0], scene.Ks[0][1, 1])
    width, height = (int(np.ceil((hi - lo)[0] * f)), int(np.ceil((hi - lo)[1] * f)))
    K_fine = np.array([[f, 0, -lo[0] * f], [0, f, -lo[1] * f], [0, 0, 1]], np.float32)
    rows, gaps = [], []
    for view in scene.test_indices:
        lens_camera = scene_camera(scene, int(view), shift)
        ours, _ = render_splats_exact(model, lens_camera, background=scene.background)
        fine_camera = Camera(jnp.asarray(K_fine), lens_camera.world_to_camera, width, height)
        fine, _ = render_splats_exact(model, fine_camera, background=scene.background, eps2d=0.3 * args.factor ** 2)
        exact = _bilinear(np.asarray(fine.image, np.float64), directions[:, 0] * f + K_fine[0, 2],
                          directions[:, 1] * f + K_fine[1, 2]).reshape(scene.height, scene.width, -1)
        ours = np.clip(np.asarray(ours.image, np.float64), 0, 1)
        exact = np.clip(exact, 0, 1)
        target = scene.images[view] / 255.0
        gaps.append(np.mean((ours - exact) ** 2))
        rows.append(dict(view=scene.names[view], first_order_vs_exact_db=round(_psnr(ours, exact), 2),
                         first_order_vs_image_db=round(_psnr(ours, target), 3),
                         exact_vs_image_db=round(_psnr(exact, target), 3)))
        print(json.dumps(rows[-1]), flush=True)
    print(json.dumps(dict(ply=args.ply, lens=args.lens if args.scene is None else str(path), factor=args.factor, fine_size=[width, height],
                          first_order_vs_exact_db=round(float(-10 * np.log10(np.mean(gaps))), 2),
                          first_order_vs_image_db=round(float(np.mean([r["first_order_vs_image_db"] for r in rows])), 3),
                          exact_vs_image_db=round(float(np.mean([r["exact_vs_image_db"] for r in rows])), 3))))


if __name__ == "__main__":
    main()
