"""``cusgs-render-ply``: render a standard 3DGS PLY at a scene's cameras and score it.

The scene may be in any layout ``cusgs-train`` reads (COLMAP, Blender, nerfstudio;
``--format``, detected by default: :mod:`cusgs_jax.data.layouts`). The PLY may come
from any tool (graphdeco, gsplat, our exporter); it is taken to be in the frame of
the scene's poses, which is therefore NOT normalised (docs/formats.md#scene-scale). Held-out
views are every ``--holdout-every``-th image, as ``cusgs-train`` holds them out
(a Blender scene's test frames); ``--all`` scores every image. PSNR/SSIM per view
and their means go to stdout as JSON; ``--out-dir`` also writes ``<image>.png``
(render | ground truth). Only argparse is imported before the arguments are
parsed, so ``--help`` does not load JAX.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

from cusgs_jax.app.argtypes import in_cli_terms, int_at_least, number_in
from cusgs_jax.config import CAMERA_FRAMES, DataConfig
from cusgs_jax.errors import UserError

__all__ = ["main", "evaluate_ply"]

PROG = "cusgs-render-ply"
#: cusgs-train's option names in the loaders' messages → this tool's flags
FLAGS = {"data.path": "--scene", "data.format": "--format", "data.downscale": "--downscale",
         "data.holdout_every": "--holdout-every", "splat.background": "--background", "data.undistort": "--undistort"}


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Render a standard 3DGS PLY at the held-out cameras of a scene (COLMAP, Blender or nerfstudio; "
                    "in the frame of its poses, not normalised) and print per-view and mean PSNR/SSIM as JSON.")
    ap.add_argument("ply", help="standard 3DGS PLY (x y z f_dc_* f_rest_* opacity scale_* rot_*)")
    ap.add_argument("--scene", "--colmap", dest="scene", required=True, metavar="SCENE",
                    help="scene folder: COLMAP (images/, sparse/0/), Blender (transforms_train.json) or nerfstudio "
                         "(transforms.json); --colmap is its old, deprecated name")
    ap.add_argument("--format", default="auto", choices=("auto", "colmap", "blender", "nerfstudio"),
                    help="the scene's layout (default: detected from the files present)")
    ap.add_argument("--downscale", type=int_at_least(1), default=1, metavar="D",
                    help="load images at 1/D resolution (images_D/ if present), intrinsics scaled (default 1)")
    ap.add_argument("--holdout-every", type=int_at_least(0), default=8, metavar="N",
                    help="score every N-th image (index %% N == 0), as cusgs-train holds out; 0: all (default 8)")
    ap.add_argument("--all", action="store_true", help="score every image")
    ap.add_argument("--undistort", default=DataConfig.undistort, choices=CAMERA_FRAMES,
                    help="distorted cameras: crop to the valid rectangle, keep the frame and score only its "
                         "valid pixels, or keep the images and render through the lens (data.undistort; "
                         "default %(default)s)")
    ap.add_argument("--out-dir", default=None, metavar="DIR", help="write <image>.png: render | ground truth")
    ap.add_argument("--background", type=number_in(0.0, 1.0), nargs=3, default=None, metavar=("R", "G", "B"),
                    help="background colour in [0, 1] (also under images with alpha; default: the layout's, "
                         "white for Blender scenes and black otherwise)")
    ap.add_argument("--sh-degree", type=int_at_least(0), default=None, metavar="D",
                    help="evaluate SH up to degree D (default: the PLY's)")
    ap.add_argument("--antialiased", action="store_true", help="gsplat's antialiased mode (default: classic)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def evaluate_ply(ply, scene_path, *, downscale: int = DataConfig.downscale, holdout_every: int = DataConfig.holdout_every,
                 all_views: bool = False,
                 out_dir=None, background=None, sh_degree: int | None = None,
                 antialiased: bool = False, progress: bool = True, format: str = DataConfig.format,
                 undistort: str = DataConfig.undistort) -> dict:
    """Render ``ply`` at the scene's held-out (or every) camera; PSNR/SSIM per view and mean.

    ``background`` None: the layout's default (white for Blender scenes, black otherwise).
    ``undistort``: ``data.undistort`` for distorted cameras; with "mask" PSNR and SSIM run over the
    valid pixels only (``SceneData.valid``).

    Returns:
      {"ply", "scene", "dataset_format", "split", "num_gaussians", "sh_degree", "evaluated_on":
       "holdout"|"all", "holdout_every", "num_views", "width", "height", "background", "psnr", "ssim",
       "per_view": [{"name", "psnr", "ssim"}], "seconds"}.
    Raises:
      UserError: a bad PLY (:class:`cusgs_jax.io.PlyError`), scene (SceneError) or setting.
    """
    import time

    import imageio.v3 as iio
    import numpy as np
    from tqdm import tqdm

    # lazy: these import JAX; keeps cusgs-render-ply --help free of it
    from cusgs_jax.data.loader import load_scene
    from cusgs_jax.eval import metrics
    from cusgs_jax.io import read_ply, render_splats_exact

    start = time.perf_counter()
    model = read_ply(ply)  # before the scene: a bad PLY fails fast
    every = 0 if all_views or holdout_every <= 1 else holdout_every
    # the scene as cusgs-train loads it with these settings (SSIM's 11x11 pixels checked before any render)
    data = DataConfig(path=str(scene_path), format=format, downscale=downscale, holdout_every=every, undistort=undistort)
    scene = load_scene(scene_path, data, background=None if background is None else tuple(background),
                       downscale_option="--downscale")
    background = scene.background
    views = scene.test_indices if every else np.arange(scene.num_images)
    degree = model.sh_degree if sh_degree is None else sh_degree
    model, shift = _recentred(model, scene)
    out_dir = None if out_dir is None else pathlib.Path(out_dir)
    if out_dir is not None:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UserError(f"--out-dir {out_dir}: cannot create it ({e.strerror or e})") from e

    per_view, pairs = [], None
    for view in tqdm(views, desc="render", unit="view", disable=not progress):
        out, pairs = render_splats_exact(model, _camera(scene, int(view), shift), background=background,
                                         sh_degree=degree, pairs_per_gaussian=pairs, antialiased=antialiased)
        image = np.clip(np.asarray(out.image, np.float32), 0.0, 1.0)
        target = scene.images[view].astype(np.float32) / 255.0
        valid = None if scene.valid is None else scene.valid[view]
        per_view.append(dict(name=scene.names[view], psnr=float(metrics.psnr(image, target, mask=valid)),
                             ssim=float(metrics.ssim(image, target, mask=valid))))
        if out_dir is not None:
            pair = (np.concatenate([image, target], axis=1) * 255).round().astype(np.uint8)
            # train/r_0.png → train_r_0.png: a Blender scene's train and test frames share file names
            iio.imwrite(out_dir / ("_".join(pathlib.PurePosixPath(scene.names[view]).with_suffix("").parts) + ".png"),
                        pair)
    return dict(
        ply=str(ply), scene=str(scene.path), dataset_format=scene.dataset_format,
        split=scene.split if every else "none", num_gaussians=model.num_gaussians, sh_degree=degree,
        evaluated_on="holdout" if every else "all", holdout_every=every, num_views=len(per_view),
        width=scene.width, height=scene.height, background=list(background),
        psnr=float(np.mean([r["psnr"] for r in per_view])), ssim=float(np.mean([r["ssim"] for r in per_view])),
        per_view=per_view, seconds=round(time.perf_counter() - start, 3))


def _recentred(model, scene):
    """The model moved by −c (c = mean camera centre, float64): :func:`cusgs_jax.io.recentre_splats`."""
    from cusgs_jax.io import recentre_splats  # lazy: cusgs_jax.io imports JAX; keeps --help free of it

    return recentre_splats(model, scene.camera_centers.mean(axis=0))


def _camera(scene, view: int, shift):
    """The scene's camera ``view`` in the frame moved by −``shift``: :func:`cusgs_jax.io.scene_camera`."""
    from cusgs_jax.io import scene_camera  # lazy: cusgs_jax.io imports JAX; keeps --help free of it

    return scene_camera(scene, view, shift)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-render-ply PLY --scene SCENE [--format auto] [--downscale D] [--holdout-every 8 | --all]
    [--out-dir DIR] [--background R G B] [--sh-degree D] [--antialiased] [--quiet]``."""
    ap = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = ap.parse_args(argv)
    if any(a == "--colmap" or a.startswith("--colmap=") for a in argv):
        print(f"{PROG}: warning: --colmap is deprecated (it reads every layout): use --scene", file=sys.stderr)
    try:
        result = evaluate_ply(args.ply, args.scene, downscale=args.downscale, holdout_every=args.holdout_every,
                              all_views=args.all, out_dir=args.out_dir,
                              background=None if args.background is None else tuple(args.background),
                              sh_degree=args.sh_degree, antialiased=args.antialiased, progress=not args.quiet,
                              format=args.format, undistort=args.undistort)
    except UserError as e:  # a bad PLY, scene or setting: one line, exit 2 (as every CLI)
        ap.exit(2, f"{PROG}: error: {in_cli_terms(str(e), FLAGS)}\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
