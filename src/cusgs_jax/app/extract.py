"""``cusgs-extract``: the command-line front end of :func:`cusgs_jax.extract.extract_scene`: loads SCENE as
:func:`cusgs_jax.data.loader.load_scene` does with these flags, then describes its images.

Imports only the (JAX-free) extraction package and the scene loader, so ``cusgs-extract --help`` is fast.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from cusgs_jax.app.argtypes import in_cli_terms, int_at_least
from cusgs_jax.config import CAMERA_FRAMES, DataConfig
from cusgs_jax.errors import UserError
from cusgs_jax.data.loader import load_scene
from cusgs_jax.extract import MODELS, extract_scene

__all__ = ["main"]

PROG = "cusgs-extract"
#: cusgs-train's option names in the loaders' messages → this tool's arguments
FLAGS = {"data.path": "SCENE", "data.format": "--format", "data.downscale": "--downscale",
         "data.undistort": "--undistort"}


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Extract dense per-view feature maps into SCENE/features/MODEL/ "
                    "(one .npy per image + meta.json).")
    ap.add_argument("scene", metavar="SCENE", help="scene folder: COLMAP (images/, sparse/0/), Blender (transforms_train.json) "
                                  "or nerfstudio (transforms.json)")
    ap.add_argument("--model", required=True, choices=MODELS)
    ap.add_argument("--format", default="auto", choices=("auto", "colmap", "blender", "nerfstudio"),
                    help="the scene's layout (default: detected from the files present)")
    ap.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=None,
                    help="feature map size (default: the image size; vgg16: 1/4 of it; "
                         "clip/dinov2: patch grid)")
    ap.add_argument("--lab", action="store_true",
                    help="daisy/hog/gabor: describe each CIE-Lab channel (3x the dimension)")
    ap.add_argument("--overwrite", action="store_true", help="replace existing features")
    ap.add_argument("--dtype", choices=("float16", "float32"), default="float16")
    ap.add_argument("--downscale", type=int_at_least(1), default=1, metavar="D", help="load images at 1/D resolution")
    ap.add_argument("--undistort", default=DataConfig.undistort, choices=CAMERA_FRAMES,
                    help="distorted cameras: crop to the valid rectangle, keep the frame and mask it, or keep the "
                         "images as captured (lens), as the training run's data.undistort (default %(default)s)")
    ap.add_argument("--dim", type=int, default=None, help="semantic: vector dimension (32)")
    ap.add_argument("--layer", default=None,
                    help="vgg16: the VGG16 tap, relu1_2|relu2_2|relu3_3|relu4_3|relu5_3 (relu3_3)")
    ap.add_argument("--weights", default=None,
                    help="clip/dinov2: LOCAL weights, a checkpoint file or the folder holding it "
                         "(open_clip for clip, timm for dinov2); nothing is downloaded")
    ap.add_argument("--arch", default=None, help="clip: open_clip architecture (ViT-B-16); "
                                                 "dinov2: timm architecture (vit_small_patch14_dinov2)")
    ap.add_argument("--device", default=None, help="clip/dinov2: torch device (cpu)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-extract SCENE --model daisy|hog|gabor|semantic|vgg16|clip|dinov2
    [--resolution W H] [--lab] [--overwrite] [--dtype float16|float32] [--downscale D]
    [--weights PATH] [--arch ARCH] [--dim 16] [--layer relu3_3] [--device cpu] [--quiet]``."""
    ap = _parser()
    args = ap.parse_args(argv)

    options: dict[str, Any] = {}
    if args.lab:
        if args.model not in ("daisy", "hog", "gabor"):
            ap.error(f"--lab applies to daisy, hog and gabor, not {args.model}")
        options["lab"] = True
    for key in ("dim", "layer", "weights", "arch", "device"):
        if getattr(args, key) is not None:
            options[key] = getattr(args, key)
    try:
        # every view as a run loads it; its initial points are not needed (2 random ones, never carved)
        data = DataConfig(path=args.scene, format=args.format, downscale=args.downscale, holdout_every=0,
                          random_points=2, carve="none", undistort=args.undistort)
        s = extract_scene(load_scene(args.scene, data, downscale_option="--downscale"), args.model,
                          resolution=args.resolution, dtype=args.dtype, overwrite=args.overwrite,
                          progress=not args.quiet, **options)
    except UserError as e:  # bad scene, features or options: one line, exit 2 (as cusgs-train)
        ap.exit(2, f"{PROG}: error: {in_cli_terms(str(e), FLAGS)}\n")
    print(f"{s.model} features -> {s.folder}\n"
          f"  {s.num_views} views, {s.resolution[0]}x{s.resolution[1]}x{s.dim} {s.dtype}, "
          f"{100 * s.valid_fraction:.1f}% pixels with a target\n"
          f"  {1000 * s.seconds_per_view:.1f} ms/view, {s.seconds:.2f} s total")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
