"""``cusgs-export``: bake a trained run into a standard 3DGS PLY that every viewer reads.

``cusgs-export RUN_DIR OUT.ply [--sh-degree 3] [--directions 64] [--min-opacity 0.005]
[--views auto|cameras|sphere] [--colmap-frame | --normalised-frame]`` loads the
newest checkpoint of a run folder (:func:`cusgs_jax.app.load_run.load_trained`;
no scene images needed), decodes every anchor from ``--directions`` sphere
directions (SH colours) and from the training cameras that see it (one opacity
and one covariance; the sphere when no camera is known or with ``--views
sphere``), drops the Gaussians that are never visible (:mod:`cusgs_jax.model.bake`,
whose docstring gives and measures every choice), moves the result to the
COLMAP frame of the scene (default; the frame a COLMAP-based viewer or
``cusgs-render-ply --colmap`` expects) and writes it
(:func:`cusgs_jax.io.write_ply`). A JSON summary goes to stdout. Only argparse
is imported before the arguments are parsed, so ``--help`` does not load JAX; a
:class:`~cusgs_jax.errors.UserError` is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import pathlib
from collections.abc import Sequence

from cusgs_jax.app.argtypes import int_at_least, number_in
from cusgs_jax.errors import UserError

__all__ = ["main", "export_run"]

PROG = "cusgs-export"


def _sh_degree(text: str) -> int:
    if text not in ("0", "1", "2", "3"):
        raise argparse.ArgumentTypeError(f"expected 0, 1, 2 or 3, got {text!r}")
    return int(text)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Bake a trained cusgs-train run (anchors decoded by MLPs per view) into a standard 3DGS PLY "
                    "(SH colours fitted over view directions) and print a JSON summary.")
    ap.add_argument("run_dir", metavar="RUN_DIR", help="output folder of a cusgs-train run (holds checkpoints/)")
    ap.add_argument("out", metavar="OUT.ply", help="PLY file to write (its folder is created)")
    ap.add_argument("--sh-degree", type=_sh_degree, default=3, metavar="D", help="SH degree 0-3 (default 3)")
    ap.add_argument("--directions", type=int_at_least(1), default=64, metavar="N",
                    help="view directions per anchor (Fibonacci sphere), at least (D+1)^2 (default 64)")
    ap.add_argument("--min-opacity", type=number_in(0.0, 1.0, include_high=False), default=0.005, metavar="O",
                    help="drop Gaussians whose opacity is <= O from every view (default 0.005)")
    ap.add_argument("--views", choices=("auto", "cameras", "sphere"), default="auto",
                    help="average opacity and shape over the training cameras that see each anchor, or over the "
                         "sphere directions; auto: cameras when the run (or its scene) gives them (default)")
    ap.add_argument("--step", type=int_at_least(0), default=None, metavar="S",
                    help="export checkpoint S instead of the newest")
    ap.add_argument("--chunk", type=int_at_least(1), default=1024, metavar="A",
                    help="anchors baked per batch (memory grows with A x offsets x (directions + cameras); "
                         "default 1024)")
    frame = ap.add_mutually_exclusive_group()
    frame.add_argument("--colmap-frame", dest="colmap_frame", action="store_true", default=True,
                       help="write in the scene's COLMAP frame (default)")
    frame.add_argument("--normalised-frame", "--normalized-frame", dest="colmap_frame", action="store_false",
                       help="write in the normalised training frame (camera extent 1, centred on the cameras)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def export_run(run_dir, out, *, sh_degree: int = 3, directions: int = 64, min_opacity: float = 0.005,
               colmap_frame: bool = True, views: str = "auto", step: int | None = None, chunk_anchors: int = 1024,
               progress: bool = True) -> dict:
    """Bake the run's newest (or ``step``) checkpoint into the standard PLY ``out``.

    Returns:
      {"ply", "run", "step", "frame": "colmap"|"normalised", "gaussians", "dropped" (never visible:
       opacity ≤ min_opacity from every view), "considered" (alive anchors × N), "anchors",
       "sh_degree", "directions", "min_opacity", "views": "cameras"|"sphere", "cameras" (how many), "cameras_from" ("checkpoint",
       the scene folder, or null), "appearance": "mean"|"none", "background" and "antialiased" (the run's
       splatter settings), "file_mb", "checkpoint_mb", "seconds"}.
    Raises:
      UserError: not a run folder, no or damaged checkpoint, no world transform for
        the COLMAP frame, a bad setting, or an unwritable output.
    """
    import dataclasses
    import time

    import numpy as np
    from tqdm import tqdm

    from cusgs_jax.app.load_run import load_trained
    from cusgs_jax.io import write_ply
    from cusgs_jax.model.bake import bake_splats, to_colmap_frame
    from cusgs_jax.splat.sh import num_sh_coeffs

    start = time.perf_counter()
    if directions < num_sh_coeffs(sh_degree):
        raise UserError(f"--directions {directions} cannot determine the {num_sh_coeffs(sh_degree)} SH coefficients "
                        f"of degree {sh_degree}: pass --directions ≥ {num_sh_coeffs(sh_degree)} (64 is the default)")
    out = pathlib.Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create the folder of {out} ({e.strerror or e})") from e
    model = load_trained(run_dir, step=step)
    if views == "cameras" and model.cameras is None:
        raise UserError(f"{model.run_dir}: neither its checkpoint nor its scene ({model.cfg.data.path or 'the demo'}) "
                        "gives the training cameras; export with --views sphere")
    cameras = model.cameras if views != "sphere" else None
    if colmap_frame and model.world is None:
        raise UserError(f"{model.run_dir} records no world transform (eval.json or checkpoint metadata): the COLMAP "
                        "frame is unknown; export with --normalised-frame")
    with tqdm(total=model.num_anchors, desc="bake", unit="anchor", disable=not progress) as bar:
        splats, summary = bake_splats(model.anchors, model.nets, model.cfg.model.decoder(), sh_degree=sh_degree,
                                      directions=directions, min_opacity=min_opacity, chunk_anchors=chunk_anchors,
                                      cameras=cameras, frustum_margin=model.cfg.model.frustum_margin,
                                      progress=bar.update)
    if colmap_frame:
        means, log_scales, quats, sh = to_colmap_frame(np.asarray(splats.means), np.asarray(splats.log_scales),
                                                       np.asarray(splats.quats), np.asarray(splats.sh), model.world)
        splats = dataclasses.replace(splats, means=means.astype(np.float32), log_scales=log_scales.astype(np.float32),
                                     quats=quats.astype(np.float32), sh=sh.astype(np.float32))
    path = write_ply(out, splats)
    dropped = summary.considered - summary.gaussians
    return dict(
        ply=str(path), run=str(model.run_dir), step=model.step, frame="colmap" if colmap_frame else "normalised",
        gaussians=summary.gaussians, dropped=dropped, considered=summary.considered, anchors=model.num_anchors,
        sh_degree=sh_degree, directions=directions, min_opacity=min_opacity,
        views="cameras" if cameras is not None else "sphere", cameras=summary.cameras,
        cameras_from=model.cameras_from if cameras is not None else None,
        appearance="mean" if "appearance" in model.nets else "none",
        # how the run rendered (cusgs-render-ply --background R G B [--antialiased] to score it the same way)
        background=list(model.cfg.splat.background_color), antialiased=bool(model.cfg.splat.antialiased),
        file_mb=round(pathlib.Path(path).stat().st_size / 2**20, 3),
        checkpoint_mb=round(model.checkpoint_bytes / 2**20, 3), seconds=round(time.perf_counter() - start, 3))


class _WarningLines:
    """While active: the library's warnings (e.g. a run without a recorded configuration) as
    ``cusgs-export: warning: …`` lines on stderr; the logger is restored afterwards."""

    def __enter__(self):
        import logging
        import sys

        self.logger = logging.getLogger("cusgs_jax")
        self.handler = logging.StreamHandler(sys.stderr)
        self.handler.setFormatter(logging.Formatter(f"{PROG}: warning: %(message)s"))
        self.handler.setLevel(logging.WARNING)
        self.propagate = self.logger.propagate
        self.logger.addHandler(self.handler)
        self.logger.propagate = False
        return self

    def __exit__(self, *exc):
        self.logger.removeHandler(self.handler)
        self.logger.propagate = self.propagate
        return False


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: ``cusgs-export RUN_DIR OUT.ply [--sh-degree D] [--directions N] [--min-opacity O] [--views V] [--step S]
    [--chunk A] [--colmap-frame | --normalised-frame] [--quiet]``."""
    ap = _parser()
    args = ap.parse_args(argv)
    try:
        with _WarningLines():
            result = export_run(args.run_dir, args.out, sh_degree=args.sh_degree, directions=args.directions,
                                min_opacity=args.min_opacity, colmap_frame=args.colmap_frame, views=args.views,
                                step=args.step,
                                chunk_anchors=args.chunk, progress=not args.quiet)
    except UserError as e:  # a bad run folder, checkpoint or setting: one line, exit 2 (as every CLI)
        ap.exit(2, f"{PROG}: error: {e}\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
