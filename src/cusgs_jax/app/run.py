"""One training run (imperative shell): ``run(cfg, output_dir)`` = setup → start → train → finalise.

``run`` takes a :class:`cusgs_jax.config.Config` and writes the run folder that
:mod:`cusgs_jax.run_folder` describes: the training log (``metrics.jsonl``; a resumed run first drops the
rows after the restored step), the held-out curve, ``eval.json`` (:class:`~cusgs_jax.run_folder.EvalRecord`),
renders, checkpoints and the PSC banks. The stages live in their own modules:
:func:`cusgs_jax.app.session.setup` (what the run starts from, an immutable ``Session``),
:func:`cusgs_jax.app.loop.start` and :func:`~cusgs_jax.app.loop.train` (the loop's mutable ``Loop``), and
:func:`finalise` here (the final evaluation and the record).

``eval.json``'s ``time`` (seconds per stage, :mod:`cusgs_jax.app.budget`) and ``compilations`` (every
XLA compilation: count, seconds, by function, :mod:`cusgs_jax.app.compiles`) close the log too.

The run trains in the normalised world frame of :mod:`cusgs_jax.data.normalize`
(``eval.json`` records the transform as ``world_transform``), so lengths in the
configuration are in units of the scene extent.
"""

from __future__ import annotations

import logging
import pathlib

import numpy as np

from cusgs_jax.app.accelerator import accelerator_record
from cusgs_jax.app.ahead import Ahead
from cusgs_jax.app.alarms import require_trained
from cusgs_jax.app.budget import TimeBudget
from cusgs_jax.app.compiles import CompileLog, compiled_name
from cusgs_jax.app.loop import Loop, evaluate_model, evaluate_model_features, start, train
from cusgs_jax.app.session import Session, setup
from cusgs_jax.app.xla_cache import use_compilation_cache
from cusgs_jax.config import Config, require_config
from cusgs_jax.densify.base import Strategy, strategy_results
from cusgs_jax.eval.lpips import lpips_metrics
from cusgs_jax.eval.plots import CLOCK, plot_error_vs_time
from cusgs_jax.eval.views import count_parameters, model_bytes
from cusgs_jax.rendering import APPEARANCE_PROTOCOL
from cusgs_jax.run_folder import EVAL_FILE, FEATURES_DIR, FEATURES_MD, PLOT_FILE, RENDERS_DIR, EvalRecord, write_eval
from cusgs_jax.training.checkpoint import quiet_orbax

__all__ = ["run", "run_session", "setup", "start", "train", "finalise", "Session", "Loop"]

log = logging.getLogger("cusgs_jax")


def finalise(session: Session, loop: Loop) -> EvalRecord:
    """Final held-out evaluation, ``eval.json``, plots; returns the run's record."""
    cfg, out, state = session.cfg, session.out, loop.state
    save = cfg.eval.save_renders
    budget = session.budget
    with budget.stage("evaluation"):
        lpips = lpips_metrics(session.scene.width, session.scene.height)  # final evaluation only, not the curve
        anchors = state.anchors
        final = evaluate_model(session, loop, anchors, out_dir=out / RENDERS_DIR if save else None, time_renders=True,
                          lpips=lpips)
        features = (None if session.banks is None else
                    evaluate_model_features(session, loop, anchors, out_dir=out / FEATURES_DIR if save else None))
    with budget.stage("report"):
        if features is not None:
            (out / FEATURES_MD).write_text(features["markdown"])
        plot_error_vs_time(loop.curve, out / PLOT_FILE,
                           title=f"held-out PSNR vs time ({pathlib.Path(str(session.scene.path)).name})")
    with budget.stage("checkpoints"):
        session.ckpt.close()
    record = EvalRecord(
        psnr=final["psnr"], ssim=final["ssim"], **{key: final[key] for key in lpips}, per_view=final["per_view"],
        params=count_parameters(state.anchors, state.nets, session.banks),
        alive_anchors=int(np.sum(np.asarray(state.anchors.alive))), capacity=state.anchors.capacity,
        # the model alone (parameters and PSC banks) beside the checkpoint (which adds the Adam moments)
        model_bytes=model_bytes(state.anchors, state.nets, session.banks),
        checkpoint_bytes=session.ckpt.step_bytes(cfg.train.iterations), train_wall_s=session.budget.clock.total,
        render_ms_per_view=final["render_ms_per_view"],
        **strategy_results(session.strategies, loop.tallies, session.cfg),  # render_ms_before_prune, prune, densify
        loss_terms=loop.loss_tally.as_dict(), appearance=APPEARANCE_PROTOCOL,
        skipped_updates=int(state.skipped), dropped_anchors=0, dropped_gaussians=0, dropped_pairs=0,
        replayed_steps=loop.replays, deferred=loop.views.record() if loop.views is not None else None,
        recompilations=loop.recompilations + loop.render.growths
        + (loop.feature_render.growths if loop.feature_render else 0),
        capacities=loop.capacities.as_dict(), voxel_size=cfg.model.voxel_size,
        world_transform=session.world.as_dict(), iterations=cfg.train.iterations,
        batch_size=cfg.train.batch_size, devices=session.devices, width=session.scene.width,
        height=session.scene.height, held_out_views=len(session.scene.test_indices),
        evaluated_on=session.evaluated_on, dataset_format=session.scene.dataset_format, split=session.scene.split,
        background=list(cfg.splat.background_color), curve=loop.curve, curve_clock=CLOCK,
        camera_frame=session.scene.camera_frame,
        # the initial points: the scene's own, or the random rule of a layout without any (data/random_points.py)
        initial_points=session.scene.random_points or "scene_points", scene_digest=session.digest(),
        carving=None if session.scene.carving is None else session.scene.carving.as_dict(),
        # the share of the held-out pixels the metrics score: < 1 only with data.undistort=mask
        valid_pixels=1.0 if session.scene.valid is None
        else float(np.mean(session.scene.valid[session.scene.test_indices])) if len(session.scene.test_indices) else 1.0,
        features=features, accelerator=accelerator_record(), compilations=_compilations(session, loop),
        time=budget.as_dict())
    write_eval(out, record)
    log.info("%s %.2f dB, SSIM %.4f, %d anchors, %.0f s training", session.psnr_label, record.psnr,
             record.ssim, record.alive_anchors, record.train_wall_s)
    compiles = record.compilations
    if compiles is not None:
        log.info("%d XLA compilations, %.1f s (%d loaded from the persistent cache; train step %d, evaluation "
                 "renders %d)", compiles["count"], compiles["seconds"], compiles["from_cache"],
                 compiles["train_step"], compiles["evaluation_renders"])
    log.info("%s", budget.line())
    require_trained(record.skipped_updates, int(state.step), str(out / EVAL_FILE))
    return record


def _compilations(session: Session, loop: Loop) -> dict | None:
    """``eval.json``'s ``compilations``: :meth:`CompileLog.summary` with the train step's and the
    evaluation render's counts (attributed by their jitted functions, :func:`compiled_name`); None when the
    run's budget keeps no compile log."""
    compiles = session.budget.compiles
    if compiles is None:
        return None
    steps = {compiled_name(program) for program in loop.programs.values()}
    render = (loop.feature_render or loop.render).program()
    return dict(compiles.summary(), train_step=sum(compiles.count(name) for name in steps),
                evaluation_renders=compiles.count(render))


def run(cfg: Config, output_dir, progress_label: str = "train", extra_strategies: tuple[Strategy, ...] = (),
        started: float | None = None, loss_terms=()) -> EvalRecord:
    """Train, checkpoint and evaluate; returns the run's record (``eval.json``: :class:`~cusgs_jax.run_folder.EvalRecord`).

    :func:`run_session` without the session and loop; :func:`cusgs_jax.train` (``app/api.py``) is the library's
    entry, which returns the model too.
    """
    return run_session(cfg, output_dir, progress_label=progress_label, strategies=extra_strategies,
                       started=started, loss_terms=loss_terms)[2]


def run_session(cfg: Config, output_dir, *, progress_label: str = "train", strategies: tuple[Strategy, ...] = (),
                started: float | None = None, loss_terms=()) -> tuple[Session, Loop, EvalRecord]:
    """Train, checkpoint and evaluate: setup → start → train → finalise; returns the session, the loop as it
    ended and the run's record (``eval.json``: :class:`~cusgs_jax.run_folder.EvalRecord`).

    ``progress_label`` names the progress bar (a sweep labels each job's bar); ``strategies`` and ``loss_terms``
    are research code's own densification strategies and loss terms (see :func:`setup`); ``started``: the
    ``time.perf_counter()`` at which the process began, so the ``time`` budget covers the imports and
    Hydra's composition too (its ``startup``; ``cusgs-train`` passes it to a process's first run). The
    programs the loop will need are compiled on a background thread (``train.compile_ahead``,
    :mod:`cusgs_jax.app.ahead`). While it runs, the noise orbax repeats after a failed checkpoint save
    or read is dropped (:func:`quiet_orbax`).
    """
    require_config(cfg, "run")
    with quiet_orbax(), CompileLog() as compiles:
        budget = TimeBudget(compiles, start=started)
        with budget.stage("startup"):
            cache = use_compilation_cache(cfg.train.compilation_cache)
        log.debug("persistent compilation cache: %s", cache or "off")
        with Ahead(on_wait=budget.waited, enabled=cfg.train.compile_ahead) as ahead:
            session = setup(cfg, output_dir, strategies, budget, ahead, loss_terms=loss_terms)
            loop = start(session)
            try:
                train(session, loop, progress_label)
                return session, loop, finalise(session, loop)
            except BaseException:
                session.ckpt.close_after_error()
                raise
