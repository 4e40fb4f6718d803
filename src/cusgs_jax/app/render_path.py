"""``cusgs-render-path``: render a trained run along a camera path to an MP4 and PNG frames (after nerfstudio's
``ns-render camera-path``).

The path goes around the run's training cameras (:func:`cusgs_jax.cameras.camera_path`): ``orbit`` circles the
point they look at, ``interpolate`` passes through each of them in order (positions linearly, rotations by slerp).
Every frame is rendered by :func:`cusgs_jax.render` with capacities fitted to the whole path once
(:func:`cusgs_jax.fit_render`), in batches of ``--batch`` views. The video needs the ``video`` extra
(``imageio-ffmpeg``, which ships its own ffmpeg); the PNG frames need nothing more. Only argparse is imported
before the arguments are parsed, so ``--help`` does not load JAX.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

from cusgs_jax.app.argtypes import int_at_least, number_in
from cusgs_jax.errors import UserError

__all__ = ["main", "render_path"]

PROG = "cusgs-render-path"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Render a cusgs-train run along a camera path (MP4 + PNG).")
    ap.add_argument("run", help="a cusgs-train run folder (it holds checkpoints/)")
    ap.add_argument("--path", default="orbit", choices=("orbit", "interpolate"),
                    help="orbit: a circle around what the training cameras look at; interpolate: through each "
                         "training camera in turn (default orbit)")
    ap.add_argument("--frames", type=int_at_least(2), default=60, metavar="N", help="frames (default 60)")
    ap.add_argument("--fps", type=number_in(1.0, 240.0), default=30.0, help="video frame rate (default 30)")
    ap.add_argument("--size", type=int_at_least(8), nargs=2, default=None, metavar=("W", "H"),
                    help="frame size (default the training images')")
    ap.add_argument("--elevation", type=number_in(-89.0, 89.0), default=20.0, metavar="DEG",
                    help="the orbit's elevation in degrees (default 20)")
    ap.add_argument("--appearance", default="mean",
                    help="the appearance embedding: mean, nearest (the nearest training camera's) or a training "
                         "view's index (default mean: a path between views borrows no single one)")
    ap.add_argument("--batch", type=int_at_least(1), default=8, metavar="B", help="views per render call (default 8)")
    ap.add_argument("--out", default=None, metavar="DIR", help="output folder (default RUN/path_<path>)")
    ap.add_argument("--no-video", action="store_true", help="write the PNG frames only")
    return ap


def _appearance(text: str):
    if text in ("mean", "nearest"):
        return text
    try:
        return int(text)
    except ValueError:
        raise UserError(f"--appearance {text!r}: give mean, nearest or a training view's index") from None


def render_path(run, *, path: str = "orbit", frames: int = 60, fps: float = 30.0, size=None,
                elevation: float = 20.0, appearance="mean", batch: int = 8, out=None, video: bool = True) -> dict:
    """Render run folder ``run`` along a camera path; writes ``frame_#####.png`` (and ``path.mp4``) into ``out``.
    Returns {"frames", "out", "video" (path or None), "size": [W, H]}."""
    import imageio.v3 as iio
    import jax
    import numpy as np
    from tqdm import tqdm

    import cusgs_jax as cg

    model = cg.load_trained(run)
    if model.cameras is None:
        raise UserError(f"{run}: the run records no training cameras (an old run whose scene is gone); a path "
                        "needs them")
    width, height = size or (model.cameras.width, model.cameras.height)
    cameras = cg.camera_path(model.cameras, path, frames, width=width, height=height, elevation_degrees=elevation)
    if isinstance(appearance, int) and not 0 <= appearance < len(model.cameras.world_to_camera):
        raise UserError(f"--appearance {appearance}: the run has {len(model.cameras.world_to_camera)} training views "
                        "(indices from 0)")
    out = pathlib.Path(out or pathlib.Path(run) / f"path_{path}")
    out.mkdir(parents=True, exist_ok=True)
    if video:
        try:
            import imageio_ffmpeg  # noqa: F401 - the video writer's ffmpeg
        except ImportError:
            raise UserError("the MP4 needs the video extra: pip install 'cusgs-jax[video]' (imageio-ffmpeg ships its "
                            "own ffmpeg), or pass --no-video for the PNG frames only") from None
    capacities = cg.fit_render(model, cameras, appearance=appearance)
    render = jax.jit(lambda views: cg.render(model, views, capacities=capacities, appearance=appearance))
    images = []
    for start in tqdm(range(0, frames, batch), desc=PROG, unit="batch"):
        views = jax.tree_util.tree_map(lambda x: x[start:start + batch], cameras)
        rendered = render(views)
        if int(np.max([np.max(np.asarray(v)) for v in rendered.dropped.values()])):  # fitted to every frame
            raise RuntimeError("a frame dropped work with capacities fitted to it")
        for k, image in enumerate(np.asarray(rendered.image)):
            frame = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
            iio.imwrite(out / f"frame_{start + k:05d}.png", frame)
            images.append(frame)
    video_path = None
    if video:
        video_path = out / "path.mp4"
        # even sizes for yuv420p; macro_block_size=1 keeps odd ones as they are
        iio.imwrite(video_path, np.stack(images), fps=float(fps), codec="libx264", macro_block_size=1)
    return dict(frames=len(images), out=str(out), video=None if video_path is None else str(video_path),
                size=[int(width), int(height)])


def main(argv: Sequence[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        result = render_path(args.run, path=args.path, frames=args.frames, fps=args.fps, size=args.size,
                             elevation=args.elevation, appearance=_appearance(args.appearance), batch=args.batch,
                             out=args.out, video=not args.no_video)
    except UserError as e:  # a bad run folder or setting: one line, exit 2 (as every CLI)
        ap.exit(2, f"{PROG}: error: {e}\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
