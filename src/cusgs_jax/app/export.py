"""``cusgs-export``: bake a trained run into a standard 3DGS PLY that every viewer reads.

``cusgs-export RUN_DIR OUT.ply|OUT.spz [--format ply|spz] [--sh-degree 3] [--directions 64] [--min-opacity 0.005]
[--views auto|cameras|sphere] [--colmap-frame | --normalised-frame] [--refine K] [--scene PATH]``
loads the newest checkpoint of a run folder (:func:`cusgs_jax.io.load_run.load_trained`;
the bake needs no scene images, the refinement does), decodes every anchor from ``--directions`` sphere
directions (SH colours) and from the training cameras that see it (one opacity
and one covariance; the sphere when no camera is known or with ``--views
sphere``), drops the Gaussians that are never visible (:mod:`cusgs_jax.model.bake`,
whose docstring gives and measures every choice), moves the result to the
COLMAP frame of the scene (default; the frame a COLMAP-based viewer or
``cusgs-render-ply --scene`` expects), then refines it as plain 3DGS against the
scene's training views (``--refine K`` steps, by default 30 per training view,
:func:`cusgs_jax.io.refine_splats`; on by
default when the run's scene is found: ``--scene``, else the run's ``data.path``, else
the built-in demo scene; ``--refine 0`` writes the plain bake) and writes it: a standard PLY
(:func:`cusgs_jax.io.write_ply`), or Niantic's SPZ for an ``.spz`` name or ``--format spz``
(:func:`cusgs_jax.io.spz.write_spz`, through the optional ``gsply`` package: the ``spz`` extra).
A JSON summary goes to stdout, with the held-out
PSNR of the bake before and after refinement. Only argparse
is imported before the arguments are parsed, so ``--help`` does not load JAX; a
:class:`~cusgs_jax.errors.UserError` is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import pathlib
from collections.abc import Sequence

from cusgs_jax.app.argtypes import int_at_least, number_in
from cusgs_jax.data.demo.lens import configured_demo
from cusgs_jax.data.loader import load_scene
from cusgs_jax.errors import UserError

__all__ = ["main", "export_run", "output_format", "default_refine_steps", "DEFAULT_REFINE_EPOCHS", "FORMATS"]

PROG = "cusgs-export"

DEFAULT_REFINE_EPOCHS = 30
"""Passes over the training views when ``--refine`` is not given: K = 30 × the scene's training views
(:func:`default_refine_steps`): every view needs about as many updates, whatever their number, so a
fixed K under-refines scenes with many views (docs/export.md)."""


def default_refine_steps(train_views: int) -> int:
    """K when ``--refine`` is not given: :data:`DEFAULT_REFINE_EPOCHS` × ``train_views`` (at least 1)."""
    return max(1, DEFAULT_REFINE_EPOCHS * int(train_views))


FORMATS = ("ply", "spz")
"""Output formats: the standard 3DGS PLY, Niantic's SPZ (:mod:`cusgs_jax.io.spz`)."""


def output_format(out, fmt: str | None) -> str:
    """The format to write ``out`` in: ``fmt``, else ``spz`` for an ``.spz`` name, else ``ply``.

    Raises:
      UserError: an unknown ``fmt``, or one that contradicts the name's ``.ply`` / ``.spz`` suffix.
    """
    suffix = pathlib.Path(out).suffix.lower()
    if fmt is None:
        return "spz" if suffix == ".spz" else "ply"
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt}: expected one of {', '.join(FORMATS)}")
    if suffix in (".ply", ".spz") and suffix[1:] != fmt:
        raise UserError(f"--format {fmt} but the output {out} is named {suffix}: name it .{fmt} or drop --format")
    return fmt


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
    ap.add_argument("out", metavar="OUT", help="file to write: OUT.ply, or OUT.spz (its folder is created)")
    ap.add_argument("--format", choices=FORMATS, default=None,
                    help="ply: the standard 3DGS PLY; spz: Niantic's compressed SPZ (needs the spz extra, gsply); "
                         "default: spz for an .spz name, else ply")
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
    ap.add_argument("--refine", type=int_at_least(0), default=None, metavar="K",
                    help=f"refine the baked Gaussians as plain 3DGS for K steps against the scene's training views "
                         f"(default {DEFAULT_REFINE_EPOCHS} x the number of training views when the run's scene is "
                         f"found; 0: write the plain bake)")
    ap.add_argument("--scene", default=None, metavar="PATH",
                    help="the run's scene folder for --refine (default: the run's data.path, or the built-in demo "
                         "scene)")
    ap.add_argument("--seed", type=int_at_least(0), default=0, metavar="S",
                    help="random order of the training views during refinement (default 0)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def export_run(run_dir, out, *, sh_degree: int = 3, directions: int = 64, min_opacity: float = 0.005,
               colmap_frame: bool = True, views: str = "auto", step: int | None = None, chunk_anchors: int = 1024,
               progress: bool = True, refine: int | None = None, scene=None, seed: int = 0,
               fmt: str | None = None) -> dict:
    """Bake the run's newest (or ``step``) checkpoint into the standard PLY (or SPZ) ``out``, refined by default.

    ``refine``: refinement steps (:func:`cusgs_jax.io.refine_splats`); None: :func:`default_refine_steps`
    of the scene's training views when the scene is found, 0: the plain bake. ``scene``: the scene folder (default: the run's
    ``data.path``, or the demo scene for a demo run). Without a scene the plain bake is written and a
    warning says so. ``seed``: the refinement's view order. ``fmt``: "ply", "spz" or None
    (:func:`output_format`: from the name's suffix).

    Returns:
      {"ply" or "spz" (the path written), "format", "run", "step", "frame": "colmap"|"normalised", "gaussians",
       "dropped" (never visible:
       opacity ≤ min_opacity from every view), "considered" (alive anchors × N), "anchors",
       "sh_degree", "directions", "min_opacity", "views": "cameras"|"sphere", "cameras" (how many), "cameras_from" ("checkpoint",
       the scene folder, or null), "appearance": "mean"|"none", "background" and "antialiased" (the run's
       splatter settings), "file_mb", "checkpoint_mb", "seconds", "refine": {"steps", "scene", "frame",
       "train_views", "held_out_views", "steps_from" ("--refine" or the default's epochs), "epochs" (steps per
       training view), "psnr_run" (eval.json), "psnr_bake", "psnr_refined" (held-out,
       None without held-out views), "seconds", "first_step_seconds" (compiling included),
       "seconds_per_100_steps" (the steps after the first)} or {"steps": 0, "skipped": why}}.
    Raises:
      UserError: not a run folder, no or damaged checkpoint, no world transform for
        the COLMAP frame, a bad setting, an unwritable output, or SPZ without the gsply package.
    """
    import dataclasses
    import time

    import numpy as np
    from tqdm import tqdm

    # lazy (these import JAX): keeps cusgs-export --help free of JAX
    from cusgs_jax.io.load_run import load_trained
    from cusgs_jax.io import write_ply
    from cusgs_jax.atomic import require_writable
    from cusgs_jax.io.spz import require_gsply, write_spz
    from cusgs_jax.model.bake import bake_splats, to_colmap_frame
    from cusgs_jax.splat.sh import num_sh_coeffs

    start = time.perf_counter()
    if directions < num_sh_coeffs(sh_degree):
        raise UserError(f"--directions {directions} cannot determine the {num_sh_coeffs(sh_degree)} SH coefficients "
                        f"of degree {sh_degree}: pass --directions ≥ {num_sh_coeffs(sh_degree)} (64 is the default)")
    if refine is not None and int(refine) < 0:
        raise UserError(f"--refine {refine}: expected a number of steps ≥ 0 (0 writes the plain bake)")
    out = pathlib.Path(out)
    fmt = output_format(out, fmt)
    if fmt == "spz":
        require_gsply(out)  # before the bake and the refinement, not after
    scene_path = _scene_folder(scene) if scene is not None else None
    require_writable(out, "the output")  # before the bake and the refinement, not after
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
    if summary.gaussians == 0:
        raise UserError(f"--min-opacity {min_opacity} removed every one of the {summary.considered} Gaussians (none "
                        "reaches that opacity from the views baked): lower it (0.005 is the default)")
    if colmap_frame:
        means, log_scales, quats, sh = to_colmap_frame(np.asarray(splats.means), np.asarray(splats.log_scales),
                                                       np.asarray(splats.quats), np.asarray(splats.sh), model.world)
        splats = dataclasses.replace(splats, means=means.astype(np.float32), log_scales=log_scales.astype(np.float32),
                                     quats=quats.astype(np.float32), sh=sh.astype(np.float32))
    refined, refine_summary = _refine(splats, model, refine, scene_path, colmap_frame=colmap_frame, seed=seed,
                                      progress=progress)
    path = write_spz(out, refined) if fmt == "spz" else write_ply(out, refined)
    dropped = summary.considered - summary.gaussians
    return {fmt: str(path), "format": fmt} | dict(
        run=str(model.run_dir), step=model.step, frame="colmap" if colmap_frame else "normalised",
        gaussians=summary.gaussians, dropped=dropped, considered=summary.considered, anchors=model.num_anchors,
        sh_degree=sh_degree, directions=directions, min_opacity=min_opacity,
        views="cameras" if cameras is not None else "sphere", cameras=summary.cameras,
        cameras_from=model.cameras_from if cameras is not None else None,
        appearance="mean" if "appearance" in model.nets else "none",
        # how the run rendered (cusgs-render-ply --background R G B [--antialiased] to score it the same way)
        background=list(model.cfg.splat.background_color), antialiased=bool(model.cfg.splat.antialiased),
        file_mb=round(pathlib.Path(path).stat().st_size / 2**20, 3),
        checkpoint_mb=round(model.checkpoint_bytes / 2**20, 3), seconds=round(time.perf_counter() - start, 3),
        refine=refine_summary)


def _scene_folder(scene) -> pathlib.Path:
    """``--scene PATH`` checked: an existing folder (UserError naming the option otherwise)."""
    path = pathlib.Path(scene).expanduser()
    if not path.is_dir():
        raise UserError(f"--scene {scene}: {'no such folder' if not path.exists() else 'not a folder'} (pass the "
                        "scene folder the run was trained on: COLMAP, Blender or nerfstudio)")
    return path


def _run_scene(model) -> tuple[pathlib.Path | None, str]:
    """(the run's scene folder or None, where it came from / why not): ``data.path``, else the demo scene."""
    data = model.cfg.data
    if data.path:
        path = pathlib.Path(str(data.path)).expanduser()
        if path.is_dir():
            return path, "data.path"
        return None, f"the run's scene data.path={data.path} is not a folder here"

    path = configured_demo(data.demo)  # where cusgs-train cached it; nothing is generated here
    if (path / "scene.json").is_file():
        return path, "the built-in demo scene"
    return None, f"the run's scene, the built-in demo scene, is not in its cache folder {path}"


def _refine(splats, model, refine, scene_path, *, colmap_frame: bool, seed: int, progress: bool):
    """(the model to write, the "refine" summary): refined against the scene's training views, or as baked."""
    import dataclasses
    import logging
    import time

    import numpy as np
    from tqdm import tqdm

    from cusgs_jax.io import heldout_psnr, refine_splats  # lazy (JAX): keeps cusgs-export --help free of JAX

    log = logging.getLogger("cusgs_jax")
    if refine == 0:
        return splats, dict(steps=0, skipped="--refine 0")
    if not colmap_frame and model.world is None:
        why = ("the run records no world transform, so the scene's cameras cannot be placed in the normalised "
               "frame: wrote the unrefined bake (refinement skipped)")
        log.warning("%s", why)
        return splats, dict(steps=0, skipped=why)
    if scene_path is None:
        scene_path, found = _run_scene(model)
        if scene_path is None:
            why = f"{found}: wrote the unrefined bake (refinement skipped); pass --scene PATH to refine"
            log.warning("%s", why)
            return splats, dict(steps=0, skipped=why)
    else:
        found = "--scene"
    data, splat = model.cfg.data, model.cfg.splat
    # the scene as the run loaded it: its own data settings, at the folder found
    scene = load_scene(scene_path, dataclasses.replace(data, path=str(scene_path)), background=splat.background,
                       seed=model.cfg.train.seed)
    _require_run_scene(model, scene, scene_path)
    steps = default_refine_steps(len(scene.train_indices)) if refine is None else int(refine)
    if not colmap_frame:  # the PLY is in the normalised training frame: move the cameras there
        scene = dataclasses.replace(scene, viewmats=model.world.viewmats(scene.viewmats))
    if _run_size(model) not in ((0, 0), (scene.width, scene.height)):
        log.warning("the scene %s loads at %dx%d but the run trained at %s: refining at the scene's size",
                    scene_path, scene.width, scene.height, "x".join(map(str, _run_size(model))))
    settings = dict(background=scene.background, sh_degree=splats.sh_degree, antialiased=bool(splat.antialiased))
    before = heldout_psnr(splats, scene, **settings)
    start = time.perf_counter()
    ticks = []  # when each step ended: the first one includes compiling the step

    with tqdm(total=steps, desc="refine", unit="step", disable=not progress) as bar:
        def tick(count):
            ticks.append(time.perf_counter())
            bar.update(count)

        refined = refine_splats(splats, scene, steps, l1_weight=model.cfg.loss.l1_weight,
                                ssim_weight=model.cfg.loss.ssim_weight, seed=seed, progress=tick, **settings)
    seconds = time.perf_counter() - start
    steady = 100.0 * (ticks[-1] - ticks[0]) / (steps - 1) if steps > 1 else None
    after = heldout_psnr(refined, scene, **settings)

    def db(value):
        return None if not np.isfinite(value) else round(float(value), 3)

    run_psnr = (model.evaluation or {}).get("psnr")
    return refined, dict(
        steps=steps, steps_from="--refine" if refine is not None else f"default: {DEFAULT_REFINE_EPOCHS} epochs",
        epochs=round(steps / max(len(scene.train_indices), 1), 2),
        scene=str(scene_path), scene_from=found, frame="colmap" if colmap_frame else "normalised",
        train_views=int(len(scene.train_indices)), held_out_views=int(len(scene.test_indices)),
        psnr_run=None if run_psnr is None else round(float(run_psnr), 3), psnr_bake=db(before), psnr_refined=db(after),
        seconds=round(seconds, 3), first_step_seconds=round(ticks[0] - start, 3),
        seconds_per_100_steps=None if steady is None else round(steady, 3))


def _require_run_scene(model, scene, scene_path) -> None:
    """Refine only against the scene the run trained on: its training poses, moved into the run's
    normalised frame, must be the ones the checkpoint records (:func:`cusgs_jax.data.identity.same_poses`)."""
    import numpy as np

    from cusgs_jax.data.identity import same_poses

    if model.cameras_from != "checkpoint" or model.world is None:  # an older run: nothing recorded to compare
        return
    train = scene.train_indices
    differs = same_poses(np.asarray(model.cameras.world_to_camera), model.world.viewmats(scene.viewmats[train]))
    if differs is not None:
        trained_on = model.cfg.data.path or "the built-in demo scene"
        raise UserError(f"--scene {scene_path}: not the scene the run {model.run_dir} was trained on ({trained_on}): "
                        f"its training cameras differ ({differs}); pass the run's own scene, or --refine 0 to write "
                        "the plain bake")


def _run_size(model) -> tuple[int, int]:
    """(width, height) the run trained at (its training cameras), or (0, 0) when unknown."""
    cams = model.cameras
    return (int(cams.width), int(cams.height)) if cams is not None else (0, 0)


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
    """CLI: ``cusgs-export RUN_DIR OUT.ply|OUT.spz [--format F] [--sh-degree D] [--directions N] [--min-opacity O]
    [--views V] [--step S]
    [--chunk A] [--colmap-frame | --normalised-frame] [--refine K] [--scene PATH] [--seed S] [--quiet]``."""
    ap = _parser()
    args = ap.parse_args(argv)
    try:
        from cusgs_jax.training.checkpoint import quiet_orbax  # lazy (JAX, orbax): keeps --help free of JAX

        with _WarningLines(), quiet_orbax():  # orbax's repeats after a damaged checkpoint: dropped
            result = export_run(args.run_dir, args.out, sh_degree=args.sh_degree, directions=args.directions,
                                min_opacity=args.min_opacity, colmap_frame=args.colmap_frame, views=args.views,
                                step=args.step, chunk_anchors=args.chunk, progress=not args.quiet,
                                refine=args.refine, scene=args.scene, seed=args.seed, fmt=args.format)
    except UserError as e:  # a bad run folder, checkpoint or setting: one line, exit 2 (as every CLI)
        ap.exit(2, f"{PROG}: error: {e}\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
