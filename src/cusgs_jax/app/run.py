"""The training run (imperative shell): setup → loop → finalise.

``run(cfg, output_dir)`` takes a :class:`cusgs_jax.config.Config` and writes the run folder that
:mod:`cusgs_jax.run_folder` describes: the training log (``metrics.jsonl``: a step that would drop work
is replayed with larger capacities, :mod:`cusgs_jax.training.capacity`, so its ``dropped_*`` are 0;
a resumed run first drops the rows after the restored step), the held-out curve, ``eval.json``
(:class:`~cusgs_jax.run_folder.EvalRecord`), renders, checkpoints and the PSC banks.

The shell names no concrete strategy: it calls every strategy's hooks the same way
(:class:`cusgs_jax.densify.base.Strategy`: ``due``, ``before_first_update``, ``update`` → ``UpdateInfo``,
``log_values``, ``results``); research code adds its own through ``run(..., extra_strategies=...)``.

The learning curve, the pruning probe and the final evaluation use one renderer: the padded model
with its alive mask, at the step's work capacities (with feature models, the feature render, whose
RGB is the evaluated image), so an evaluation compiles again only when the anchor capacity changes
(the step recompiles then too), never because the model grew inside it.

``eval.json``'s ``time`` (seconds per stage, :mod:`cusgs_jax.app.budget`) and ``compilations`` (every
XLA compilation: count, seconds, by function, :mod:`cusgs_jax.app.compiles`) close the log too.

The run trains in the normalised world frame of :mod:`cusgs_jax.data.normalize`
(``eval.json`` records the transform as ``world_transform``), so lengths in the
configuration are in units of the scene extent.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import pathlib
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from cusgs_jax.app.accelerator import accelerator_record
from cusgs_jax.app.ahead import Ahead, Program
from cusgs_jax.app.foresight import Foresight
from cusgs_jax.app.alarms import loss_alarms, require_trained
from cusgs_jax.app.budget import TimeBudget
from cusgs_jax.app.compiles import CompileLog, compiled_name
from cusgs_jax.app.resolve import resolve_for_scene
from cusgs_jax.app.resume import require_not_past, resume
from cusgs_jax.app.xla_cache import use_compilation_cache
from cusgs_jax.config import Config, require, require_config
from cusgs_jax.errors import UserError
from cusgs_jax.data.scene_data import SceneData
from cusgs_jax.data.errors import SceneError
from cusgs_jax.data.features import FeatureSet
from cusgs_jax.data.identity import scene_digest
from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.training.inputs import feature_targets, load_data, load_feature_targets, make_batches
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import Probe, Strategy, Tally, strategy_results, strategy_row
from cusgs_jax.densify.factory import make_strategies
from cusgs_jax.eval.features import evaluate_features
from cusgs_jax.eval.lpips import lpips_metrics
from cusgs_jax.eval.plots import CLOCK, plot_error_vs_time
from cusgs_jax.eval.views import count_parameters, evaluate_views, model_bytes, nearest_train_view
from cusgs_jax.run_folder import (BANKS_FILE, CHECKPOINTS_DIR, CURVE_FILE, EVAL_FILE, FEATURES_DIR, FEATURES_MD,
                                  METRICS_FILE, PLOT_FILE, RENDERS_DIR, CheckpointMeta,
                                  EvalRecord, accept_hydra_record, read_eval, restore_hydra_record, write_eval)
from cusgs_jax.model.anchors import compact
from cusgs_jax.training.checkpoint import Checkpointer, quiet_orbax
from cusgs_jax.training import capacity
from cusgs_jax.training.distributed import require_single_process
from cusgs_jax.training.parallel import resolve_devices
from cusgs_jax.training.render import RgbOfFeatureRender, make_feature_render_fn, make_render_fn, most_work
from cusgs_jax.training.state import TrainState, init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera
from cusgs_jax.view.live import live_view
from cusgs_jax.view.render import ViewCamera, ViewModel, scene_cameras, view_model

log = logging.getLogger("cusgs_jax")


@dataclasses.dataclass(frozen=True)
class Session:
    """What a run starts from, as setup leaves it (immutable; the loop's state is a :class:`Loop`).

    The renderers, the budget and the compile pool are objects with their own bookkeeping (a render grows its
    capacities, the budget charges time, the pool compiles); the session's fields never change.
    """

    cfg: Config  # resolved for the scene (app/resolve.py); the grown work capacities live in ``Loop.capacities``
    out: pathlib.Path
    scene: SceneData  # in the normalised training frame (extent 1)
    world: WorldTransform  # the scene's frame (COLMAP's) → the normalised training frame
    train_idx: np.ndarray  # [V] the training views (indices into the scene's views)
    test_idx: np.ndarray  # the evaluated views: held-out ones, or training views when there are none
    feature_sets: dict[str, FeatureSet]  # {feature model: its maps of every view}
    banks: dict[str, jax.Array] | None  # {feature model: [M, D] PSC entries}; None without feature models
    targets: dict[str, jax.Array]  # {feature model: [V, h, w, D] training targets (float16 unless too large)}
    strategies: tuple[Strategy, ...]  # the densification strategies, run in this order
    tx: optax.GradientTransformation
    ckpt: Checkpointer
    budget: TimeBudget  # seconds per stage (eval.json's time) and the training clock
    ahead: Ahead | None = None  # the background compiles (app/ahead.py); None: every program compiles on its call
    render: capacity.ExactRender | RgbOfFeatureRender | None = None  # the evaluation's RGB render
    feature_render: capacity.ExactRender | None = None  # and its feature render (feature models only)
    batches: Callable[[int], dict] | None = None  # batch(step): the training views of a step (make_batches)

    @property
    def evaluated_on(self) -> str:
        return "held_out" if len(self.scene.test_indices) else "train"


@dataclasses.dataclass
class Loop:
    """The training loop's mutable state, in one place: the numeric state and what the shell counts beside it."""

    state: TrainState
    capacities: capacity.Capacities  # the step's work capacities: owned, grown and checkpointed here
    tallies: dict[str, Tally]  # {strategy name: what its updates did} (checkpointed)
    curve: list[dict] = dataclasses.field(default_factory=list)  # the learning curve (eval_curve.jsonl rows)
    recompilations: int = 0  # capacity growths (anchors, visible slots, tile pairs) that recompile
    replays: int = 0  # steps replayed because a capacity was too small
    alarmed: set[str] = dataclasses.field(default_factory=set)  # loss terms already warned about (loss_alarms)
    step_fn: Callable[[TrainState, dict], tuple[TrainState, dict]] | None = None  # built for ``capacities``
    programs: dict = dataclasses.field(default_factory=dict)  # {Capacities: the step's Program for them}


# --- setup ----------------------------------------------------------------------------------


def setup(cfg: Config, output_dir, extra_strategies: tuple[Strategy, ...] = (),
          budget: TimeBudget | None = None, ahead: Ahead | None = None) -> tuple[Session, Loop]:
    """Scene, feature targets, fresh (or resumed) state, step and renderers: ``(session, loop)``.

    ``extra_strategies``: research code's own densification strategies
    (:class:`cusgs_jax.densify.base.Strategy`, unique names), run after the configured ones
    (:func:`~cusgs_jax.densify.factory.make_strategies`); a resume must pass the same ones.
    ``budget``: where the setup's stages are charged (:func:`run` passes the run's; default a new one).
    ``ahead``: the run's background compiles (:mod:`cusgs_jax.app.ahead`): the first step and the
    evaluation render are compiled there while setup ends (default: none, each compiles on its first call).
    """
    budget = budget or TimeBudget()
    require_single_process()
    resolve_devices(cfg.train.batch_size, cfg.train.devices)  # train.devices=N with fewer devices: refused first
    out = _output_folder(output_dir)
    try:
        started = _setup(cfg, out, extra_strategies, budget, ahead)
    except UserError:  # refused: the folder's Hydra record goes back to the run it holds
        restore_hydra_record(out)
        raise
    accept_hydra_record(out)
    return started


def _setup(cfg: Config, out: pathlib.Path, extra_strategies: tuple[Strategy, ...], budget: TimeBudget,
           ahead: Ahead | None) -> tuple[Session, Loop]:
    ckpt = Checkpointer(cfg.train.checkpoint_dir or out / CHECKPOINTS_DIR)
    latest = ckpt.latest_step()
    require(not cfg.train.resume or latest is not None, "train.resume", True,
            f"there is no checkpoint to resume in {ckpt.directory}",
            "point hydra.run.dir (or train.checkpoint_dir) at the folder of the run to continue, "
            "or drop train.resume to start afresh")
    require(cfg.train.resume or latest is None, "train.resume", False,
            f"{ckpt.directory} already holds checkpoints of an earlier run (newest: step {latest})",
            "continue it with train.resume=true, or start afresh in a new folder (hydra.run.dir=...)")
    require_not_past(cfg, latest, ckpt.directory)
    if cfg.train.resume:
        read_eval(out)  # a record this version cannot read (newer, damaged) is refused here, not overwritten
    with budget.stage("load"):
        scene, world = load_data(cfg)
        cfg = resolve_for_scene(cfg, scene).cfg  # every auto setting, once (app/resolve.py)
        train_idx = scene.train_indices
    test_idx = scene.test_indices if len(scene.test_indices) else _spread(train_idx, 8)
    log.info("scene %s (%s): %d train / %d held-out views at %dx%d, %d points; extent %.4g in the scene's frame "
             "(trained in units of it), voxel size %.4g", scene.path, scene.dataset_format, len(train_idx),
             len(scene.test_indices), scene.width, scene.height, len(scene.points), 1.0 / world.scale,
             cfg.model.voxel_size)
    if not len(scene.test_indices):
        log.warning("no held-out views (data.holdout_every=%d): the reported PSNR/SSIM are measured on "
                    "training views and say nothing about novel views", cfg.data.holdout_every)
    feature_sets, banks, targets = {}, None, {}
    if cfg.features.enabled:
        with budget.stage("features"):
            feature_sets, banks = load_feature_targets(cfg.features, scene, cfg.train.seed, stage=budget.stage)
            targets = feature_targets(feature_sets, train_idx)
            banks = {name: jax.device_put(np.asarray(b, np.float32)) for name, b in banks.items()}
    strategies = make_strategies(cfg) + tuple(extra_strategies)
    names = [s.name for s in strategies]
    if len(set(names)) != len(names):
        raise ValueError(f"densification strategies need unique names (TrainState.densify is keyed by them): {names}")
    with budget.stage("init"):
        state, tx = init_train_state(cfg, scene.points, len(train_idx), scene.extent, strategies, banks)
    session = Session(cfg=cfg, out=out, scene=scene, world=world, train_idx=train_idx, test_idx=test_idx,
                      feature_sets=feature_sets, banks=banks, targets=targets, strategies=strategies, tx=tx,
                      ckpt=ckpt, budget=budget, ahead=ahead)
    with budget.stage("probe"):
        loop = Loop(state=state, capacities=_fitted_capacities(session, state),
                    tallies={name: Tally() for name in names})
    if cfg.train.resume:
        with budget.stage("checkpoints"):
            resume(session, loop)
    if cfg.train.batch_size > 1:
        log.info("%d views per step, sharded over %d of %d device(s)", cfg.train.batch_size, _devices(session),
                 jax.device_count())
    # The evaluation renders the padded model at the step's capacities with headroom (its own grow, should a
    # held-out view need more): one program per anchor capacity; with features one program for RGB and features.
    wrap = functools.partial(Program, ahead=ahead)  # its programs can be compiled ahead
    feature_render = (make_feature_render_fn(cfg, loop.capacities.for_evaluation(), wrap=wrap)
                      if cfg.features.enabled else None)
    render = (RgbOfFeatureRender(feature_render, banks) if feature_render
              else make_render_fn(cfg, loop.capacities.for_evaluation(), wrap=wrap))
    session = dataclasses.replace(session, render=render, feature_render=feature_render,
                                  batches=make_batches(scene, train_idx, cfg, targets, banks))
    # the programs the loop starts with, compiled in the background from here on
    _step_program(session, loop, loop.capacities).prepare(loop.state, session.batches(int(loop.state.step)))
    _prepare_render(session, loop, loop.state.anchors)
    return session, loop


def _step_program(session: Session, loop: Loop, capacities: capacity.Capacities) -> Program:
    """The step's :class:`~cusgs_jax.app.ahead.Program` for ``capacities`` (one per capacities: its executables
    are those of each anchor capacity it was prepared or called for)."""
    if capacities not in loop.programs:
        loop.programs[capacities] = Program(make_train_step(session.cfg, session.tx, session.strategies,
                                                               capacities), session.ahead)
    return loop.programs[capacities]


def _prepare_render(session: Session, loop: Loop, anchors) -> None:
    """Compile the evaluation render for ``anchors``' capacity in the background (``anchors``: arrays or
    ``ShapeDtypeStruct`` s of the padded model), so a held-out evaluation does not wait for it."""
    render = session.feature_render or session.render
    scene, view = session.scene, int(session.test_idx[0])
    args = (anchors, loop.state.nets, Camera.of_scene(scene, view),
            nearest_train_view(scene.camera_centers, scene.train_indices, view))
    render.program().prepare(*args, *((session.banks,) if session.feature_render else ()))


def _fitted_capacities(session: Session, state: TrainState, probes: int = 8) -> capacity.Capacities:
    """The step's first work capacities, sized by what up to ``probes`` training views (spread over
    them) need of the initial model, with headroom (:meth:`~cusgs_jax.training.capacity.Capacities.fitted`);
    the config's guesses are not used. They grow, and the step replays, when a later view needs more."""
    scene, cfg = session.scene, session.cfg
    positions = _spread(np.arange(len(session.train_idx)), probes)
    needs = most_work(state.anchors, state.nets, [(Camera.of_scene(scene, int(session.train_idx[p])), np.int32(p))
                                                  for p in positions], cfg)
    if needs["visible_anchors"] == 0:
        raise SceneError(
            f"data.path={str(scene.path)!r}: none of the {int(np.sum(np.asarray(state.anchors.alive)))} initial anchors (from the "
            f"{len(scene.points)} SfM points) is seen by any of the {len(positions)} training views probed "
            f"(spread over all {len(session.train_idx)}): the points lie behind or beside every camera, and training "
            "would only fit the background. Check that the points and the cameras come from the same reconstruction "
            "and frame (not a points file of another run, not poses read as camera-to-world where world-to-camera "
            "is meant), and that data.path names the right scene")
    fitted = capacity.Capacities.fitted(needs, state.anchors.capacity, cfg.model.n_offsets)
    log.info("work capacities from %d probed views (at most %d visible anchors, %d active Gaussians, %d tile "
             "pairs): %s", len(positions), needs["visible_anchors"], needs["active_gaussians"],
             needs["pairs"], fitted)
    return fitted


def _output_folder(output_dir) -> pathlib.Path:
    out = pathlib.Path(output_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / ".write_test").touch()
        (out / ".write_test").unlink()
    except OSError as error:
        require(False, "hydra.run.dir", str(out), f"the output folder cannot be written ({error.strerror})",
                "run from a writable folder or set hydra.run.dir=<a writable folder>")
    return out


def _spread(indices: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` entries of ``indices`` spread evenly over it."""
    return indices[np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))]


# --- the loop -------------------------------------------------------------------------------


def train(session: Session, loop: Loop, progress_label: str = "train") -> None:
    """Steps from the state's step to ``train.iterations``: update, densify, log, evaluate, checkpoint."""
    cfg = session.cfg
    iterations, start = cfg.train.iterations, int(loop.state.step)
    batches = session.batches
    cameras = scene_cameras(session.scene, session.train_idx) if cfg.train.viewer else []  # fixed during a run
    snapshot = functools.partial(_snapshot, session, loop, cameras)  # the live viewer's model as it is when called
    bar = tqdm(range(start, iterations), initial=start, total=iterations, desc=progress_label,
               disable=not cfg.train.progress, dynamic_ncols=True)
    last_log = time.perf_counter()
    foresight = Foresight(session.strategies, iterations, functools.partial(_step_program, session, loop),
                          functools.partial(_prepare_render, session, loop))
    with session.budget.stage("train_steps"):  # the first step's program, compiled during setup: waited for here
        loop.step_fn = _step_program(session, loop, loop.capacities)
        loop.step_fn.wait(loop.state, batches(start))
        if session.ahead is not None and jax.default_backend() == "cpu":
            session.ahead.settle()  # the evaluation render too: on a CPU its compile would share the steps' cores
    with open(session.out / METRICS_FILE, "a") as metrics_file, \
            open(session.out / CURVE_FILE, "a") as curve_file, live_view(cfg.train, snapshot) as live:
        for step in bar:
            with session.budget.clock:
                with session.budget.stage("train_steps"):
                    started = time.perf_counter()
                    metrics = _exact_step(session, loop, batches(step))
                    foresight.stepped(time.perf_counter() - started)
                with session.budget.stage("densify"):
                    _densify(session, loop, step + 1)
                    foresight.after(session, loop, step + 1)
            if live is not None:  # train.viewer: within its share of the wall time, not on the clock
                live.after_step()
            done = step + 1
            if done % cfg.train.log_every == 0 or done == iterations:
                row = _log_row(session, loop, done, metrics, (time.perf_counter() - last_log) / cfg.train.log_every)
                last_log = time.perf_counter()
                metrics_file.write(json.dumps(row) + "\n")
                metrics_file.flush()
                bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['train_psnr']:.2f}",
                                anchors=row["alive_anchors"], step_s=row["step_s"])
            if cfg.eval.every and (done % cfg.eval.every == 0 or done == iterations):
                with session.budget.stage("evaluation"):
                    point = _curve_point(session, loop, done)
                curve_file.write(json.dumps(point) + "\n")
                curve_file.flush()
                bar.write(f"step {done}: {_psnr_label(session)} {point['psnr']:.2f} dB at {point['wall_s']:.0f} s")
            if cfg.train.checkpoint_every and done % cfg.train.checkpoint_every == 0 and done < iterations:
                with session.budget.stage("checkpoints"):
                    _save(session, loop, done)
    bar.close()
    if session.ckpt.latest_step() != iterations:  # a resumed run that was already complete has it
        with session.budget.stage("checkpoints"):
            _save(session, loop, iterations)


def _snapshot(session: Session, loop: Loop, cameras: list[ViewCamera]) -> ViewModel:
    """What the live viewer shows of the model as it is now (anchors compacted now).

    The snapshot owns its arrays: the step donates the state's buffers, so the networks are copied
    (small MLPs) rather than shared, and the snapshot stays valid after the next step.
    """
    nets = jax.tree_util.tree_map(jnp.copy, loop.state.nets)
    return view_model(session.cfg, compact(loop.state.anchors), nets, session.banks, cameras)


def _exact_step(session: Session, loop: Loop, batch: dict) -> dict:
    """One training step on ``batch`` that dropped no work; returns its metrics (host values).

    A step that reported dropped anchors or tile pairs changed nothing; the
    capacity is grown (:meth:`cusgs_jax.training.capacity.Capacities.grown`), the step
    rebuilt and the same batch replayed.
    """
    while True:
        if loop.step_fn is None:
            loop.step_fn = _step_program(session, loop, loop.capacities)
        loop.state, metrics = loop.step_fn(loop.state, batch)
        metrics = jax.device_get(metrics)  # also charges the step's real compute time to the clock
        if not (metrics["dropped_anchors"] or metrics["dropped_gaussians"] or metrics["dropped_pairs"]):
            return metrics
        loop.capacities = loop.capacities.grown(metrics, loop.state.anchors.capacity,
                                                      session.cfg.model.n_offsets)
        loop.step_fn, loop.replays, loop.recompilations = None, loop.replays + 1, loop.recompilations + 1


def _densify(session: Session, loop: Loop, step: int) -> None:
    """Run every strategy due after ``step`` completed steps (host side, between steps).

    Before a strategy's first update its :meth:`~cusgs_jax.densify.base.Strategy.before_first_update`
    hook sees a :class:`~cusgs_jax.densify.base.Probe`; each update's
    :class:`~cusgs_jax.densify.base.UpdateInfo` is added to the strategy's tally.
    """
    for strategy in session.strategies:
        if not strategy.due(step):
            continue
        tally = loop.tallies[strategy.name]
        if tally.updates == 0:
            tally = dataclasses.replace(tally, values=dict(strategy.before_first_update(_probe(session, loop, step))))
        loop.state, info = strategy.update(loop.state, session.tx, step)
        if info.capacity_changed:
            loop.recompilations += 1  # new shapes: the jitted step retraces
        loop.tallies[strategy.name] = tally.add(info)
        log.debug("step %d: %s grew %d, pruned %d anchors%s %s", step, strategy.name, info.grown, info.pruned,
                  " (capacity changed)" if info.capacity_changed else "", dict(info.extra))
        _shrink_if_empty(session, loop, step)


def _shrink_if_empty(session: Session, loop: Loop, step: int) -> None:
    """Move the anchors to a smaller capacity when pruning left most slots dead (:func:`ops.shrunk_capacity`),
    and refit the work capacities to the smaller model, so a step pays for what is alive."""
    alive, old = int(np.sum(np.asarray(loop.state.anchors.alive))), loop.state.anchors.capacity
    new = ops.shrunk_capacity(alive, old, ladder=session.cfg.model.capacity_ladder)
    if new is None:
        return
    loop.state = ops.resize_capacity(loop.state, session.tx, new)
    loop.capacities = _fitted_capacities(session, loop.state)
    loop.step_fn, loop.recompilations = None, loop.recompilations + 1
    log.info("step %d: %d of %d anchor slots alive: capacity shrunk to %d (the step recompiles once)",
             step, alive, old, new)


def _probe(session: Session, loop: Loop, step: int) -> Probe:
    """What a strategy's ``before_first_update`` hook may measure of the run after ``step`` steps."""
    def render_ms_per_view() -> float:
        with session.budget.clock.paused(), session.budget.stage("evaluation"):
            return _evaluate(session, loop, loop.state.anchors, time_renders=True)["render_ms_per_view"]

    return Probe(step=step, render_ms_per_view=render_ms_per_view)


def _devices(session: Session) -> int:
    """Devices the step's views are sharded over (1 for a single-view step)."""
    return resolve_devices(session.cfg.train.batch_size, session.cfg.train.devices)


def _log_row(session: Session, loop: Loop, step: int, metrics: dict, step_s: float) -> dict:
    state = loop.state
    row = dict(step=step, wall_s=round(session.budget.clock.total, 3), loss=float(metrics["loss"]),
               **({"feature_loss": float(metrics["loss_feature"])} if session.banks is not None else {}),
               train_psnr=float(metrics["psnr"]), alive_anchors=int(np.sum(np.asarray(state.anchors.alive))),
               visible_anchors=int(metrics["visible_anchors"]), active_gaussians=int(metrics["active_gaussians"]),
               pairs=int(metrics["pairs"]), **strategy_row(session.strategies, loop.tallies, session.cfg),
               skipped=int(state.skipped), dropped_anchors=int(metrics["dropped_anchors"]),
               dropped_gaussians=int(metrics["dropped_gaussians"]),
               dropped_pairs=int(metrics["dropped_pairs"]), replays=loop.replays,
               recompilations=loop.recompilations, step_s=round(step_s, 4))
    loss_alarms(loop.alarmed, step, metrics)
    return row


def _evaluate(session: Session, loop: Loop, anchors, **kwargs) -> dict:
    """Held-out PSNR/SSIM of the model as it is now; ``anchors`` = ``loop.state.anchors`` (padded, alive mask)."""
    return evaluate_views(session.render, anchors, loop.state.nets, session.scene, session.test_idx, **kwargs)


def _evaluate_features(session: Session, loop: Loop, anchors, **kwargs) -> dict:
    """Feature errors of the model as it is now; ``anchors`` = ``loop.state.anchors`` (padded, alive mask)."""
    return evaluate_features(session.feature_render, anchors, loop.state.nets, session.scene, session.test_idx,
                             session.banks, session.feature_sets, **kwargs)


def _curve_point(session: Session, loop: Loop, step: int) -> dict:
    anchors = loop.state.anchors  # padded, with its alive mask: the shapes the step has (no new program)
    result = _evaluate(session, loop, anchors)
    point = dict(step=step, wall_s=session.budget.clock.total, psnr=result["psnr"], ssim=result["ssim"],
                 alive_anchors=int(np.sum(np.asarray(loop.state.anchors.alive))))
    if session.banks is not None:
        feats = _evaluate_features(session, loop, anchors, retrieval=False)["models"]
        point["feature_cosine"] = float(np.mean([m["cosine"] for m in feats.values()]))
        point["feature_l2"] = float(np.mean([m["l2"] for m in feats.values()]))
    loop.curve.append(point)
    return point


def _psnr_label(session: Session) -> str:
    return "held-out PSNR" if session.evaluated_on == "held_out" else "training-view PSNR (no held-out views)"


def _save(session: Session, loop: Loop, step: int) -> None:
    meta = CheckpointMeta(
        step=step, capacity=loop.state.anchors.capacity, wall_s=session.budget.clock.total, curve=loop.curve,
        densify={name: tally.as_dict() for name, tally in loop.tallies.items()},
        recompilations=loop.recompilations, replays=loop.replays,
        capacities=loop.capacities.as_dict(), voxel_size=session.cfg.model.voxel_size,
        # what cusgs-export needs from an unfinished run or one trained without Hydra (io/load_run.py)
        world_transform=session.world.as_dict(), config=dataclasses.asdict(session.cfg),
        train_cameras=_cameras(session, session.train_idx), scene_digest=_digest(session),
        held_out_cameras=_cameras(session, session.scene.test_indices))  # cusgs-view's camera list
    session.ckpt.save(step, loop.state, meta.to_json())
    if session.banks is not None and not (session.out / BANKS_FILE).is_file():  # what cusgs-view renders with
        np.savez(session.out / BANKS_FILE, **{name: np.asarray(b) for name, b in session.banks.items()})


def _digest(session: Session) -> str:
    """The training cameras' digest (:func:`cusgs_jax.data.identity.scene_digest`): checkpoints and eval.json."""
    scene, idx = session.scene, session.train_idx
    return scene_digest(scene.viewmats[idx], scene.Ks[idx], scene.width, scene.height)


def _cameras(session: Session, idx) -> dict:
    """Views ``idx`` in the normalised frame: {"viewmats": [V][4][4], "Ks": [V][3][3], "width", "height"}, and
    with ``data.undistort=lens`` of distorted cameras "lens": {"coeffs": [V][6], "bounds": [V][4], "fisheye"}."""
    scene = session.scene
    out = dict(viewmats=np.asarray(scene.viewmats, np.float64)[idx].tolist(),
               Ks=np.asarray(scene.Ks, np.float64)[idx].tolist(), width=int(scene.width), height=int(scene.height))
    if scene.lens is not None:
        out["lens"] = scene.lens.as_dict(idx)
    return out


# --- finalise -------------------------------------------------------------------------------


def finalise(session: Session, loop: Loop) -> EvalRecord:
    """Final held-out evaluation, ``eval.json``, plots; returns the run's record."""
    cfg, out, state = session.cfg, session.out, loop.state
    save = cfg.eval.save_renders
    budget = session.budget
    with budget.stage("evaluation"):
        lpips = lpips_metrics(session.scene.width, session.scene.height)  # final evaluation only, not the curve
        anchors = state.anchors
        final = _evaluate(session, loop, anchors, out_dir=out / RENDERS_DIR if save else None, time_renders=True,
                          lpips=lpips)
        features = (None if session.banks is None else
                    _evaluate_features(session, loop, anchors, out_dir=out / FEATURES_DIR if save else None))
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
        skipped_updates=int(state.skipped), dropped_anchors=0, dropped_gaussians=0, dropped_pairs=0,
        replayed_steps=loop.replays,
        recompilations=loop.recompilations + session.render.growths
        + (session.feature_render.growths if session.feature_render else 0),
        capacities=loop.capacities.as_dict(), voxel_size=cfg.model.voxel_size,
        world_transform=session.world.as_dict(), iterations=cfg.train.iterations,
        batch_size=cfg.train.batch_size, devices=_devices(session), width=session.scene.width,
        height=session.scene.height, held_out_views=len(session.scene.test_indices),
        evaluated_on=session.evaluated_on, dataset_format=session.scene.dataset_format, split=session.scene.split,
        background=list(cfg.splat.background_color), curve=loop.curve, curve_clock=CLOCK,
        camera_frame=session.scene.camera_frame,
        # the initial points: the scene's own, or the random rule of a layout without any (data/random_points.py)
        initial_points=session.scene.random_points or "scene_points", scene_digest=_digest(session),
        carving=None if session.scene.carving is None else session.scene.carving.as_dict(),
        # the share of the held-out pixels the metrics score: < 1 only with data.undistort=mask
        valid_pixels=1.0 if session.scene.valid is None
        else float(np.mean(session.scene.valid[session.scene.test_indices])) if len(session.scene.test_indices) else 1.0,
        features=features, accelerator=accelerator_record(), compilations=_compilations(session, loop),
        time=budget.as_dict())
    write_eval(out, record)
    log.info("%s %.2f dB, SSIM %.4f, %d anchors, %.0f s training", _psnr_label(session), record.psnr,
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
    render = (session.feature_render or session.render).program()
    return dict(compiles.summary(), train_step=sum(compiles.count(name) for name in steps),
                evaluation_renders=compiles.count(render))


def run(cfg: Config, output_dir, progress_label: str = "train", extra_strategies: tuple[Strategy, ...] = (),
        started: float | None = None) -> EvalRecord:
    """Train, checkpoint and evaluate; returns the run's record (``eval.json``: :class:`~cusgs_jax.run_folder.EvalRecord`).

    ``progress_label`` names the progress bar (a sweep labels each job's bar); ``extra_strategies``
    are research code's own densification strategies (see :func:`setup`); ``started``: the
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
            session, loop = setup(cfg, output_dir, extra_strategies, budget, ahead)
            try:
                train(session, loop, progress_label)
                return finalise(session, loop)
            except BaseException:
                session.ckpt.close_after_error()
                raise
