"""``cusgs-demo-scene``: generate the synthetic demo room (:mod:`cusgs_jax.data.demo`) as a
COLMAP scene folder, through a pinhole or a distorting lens (``--lens``, :mod:`cusgs_jax.data.demo.lens`)."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence

from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.data.demo.lens import LENSES, lens_camera, write_lens_demo

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-demo-scene OUT [--views 30 --width 160 --height 120 --seed 0 --lens pinhole
    --overwrite]``."""
    ap = argparse.ArgumentParser(prog="cusgs-demo-scene",
                                 description="Generate the synthetic demo room as a COLMAP scene.")
    ap.add_argument("out", help="output folder")
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--points", type=int, default=6000, help="surface samples (before filtering)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lens", choices=LENSES, default="pinhole",
                    help="ray cast through this lens: pinhole (the demo), opencv or simple_radial "
                         "(a distorted COLMAP camera; cusgs-train renders through it, or undistorts it with data.undistort=crop|mask)")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    try:
        kwargs = dict(seed=args.seed, num_views=args.views, width=args.width, height=args.height,
                      num_points=args.points, overwrite=args.overwrite)
        if args.lens == "pinhole":
            out = generate_demo_scene(args.out, **kwargs)
        else:
            out = write_lens_demo(args.out, *lens_camera(args.lens, args.width, args.height),
                                  lens_name=args.lens, **kwargs)
    except (FileExistsError, ValueError) as e:
        ap.exit(2, f"cusgs-demo-scene: error: {e}\n")  # bad settings: exit 2, as every CLI
    info = json.loads((out / "scene.json").read_text())
    num_objects = len(json.loads((out / "objects.json").read_text()))
    print(f"demo scene -> {out}\n"
          f"  {info['num_views']} views {info['width']}x{info['height']} ({info['camera_model']} "
          f"fx={info['intrinsics']['fx']:g} fy={info['intrinsics']['fy']:g}), {num_objects} objects\n"
          f"  {info['num_points']} points (of {info['num_points_sampled']} sampled), mean track "
          f"length {info['mean_track_length']:.2f}\n"
          f"  generated in {time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
