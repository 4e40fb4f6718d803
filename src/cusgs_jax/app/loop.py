"""The training loop: ``start(session) -> Loop`` and ``train(session, loop)``.

:func:`start` makes the loop's state from a :class:`~cusgs_jax.app.session.Session`: the fresh train state
and its optimiser (:func:`cusgs_jax.training.state.init_train_state`), the step's first work capacities
fitted to what the training views need of it, a resumed checkpoint over both (``train.resume``), and the
evaluation renders; the first step's and render's programs start compiling in the background.
:class:`Loop` holds everything that changes while the run trains, in one place.

:func:`train` steps to ``train.iterations``: a step that would drop work is replayed with larger
capacities (:mod:`cusgs_jax.training.capacity`), so the logged ``dropped_*`` are 0; the strategies'
hooks are called the same way for every strategy (:class:`cusgs_jax.densify.base.Strategy`: ``due``,
``before_first_update``, ``update`` → ``UpdateInfo``, ``log_values``, ``results``); the learning curve,
the pruning probe and the final evaluation use one renderer (the padded model with its alive mask, at the
step's work capacities with headroom), so an evaluation compiles again only when the anchor capacity
changes (the step recompiles then too), never because the model grew inside it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from cusgs_jax.app import interrupt
from cusgs_jax.app.ahead import Program
from cusgs_jax.app.ahead import specs as ahead_specs
from cusgs_jax.app.alarms import loss_alarms
from cusgs_jax.app.deferral import ViewQueue
from cusgs_jax.app.foresight import Foresight, only_removes
from cusgs_jax.app.programs import StepPrograms
from cusgs_jax.app.resume import resume
from cusgs_jax.app.session import Session, spread
from cusgs_jax.data.errors import SceneError
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import Probe, Tally, strategy_row
from cusgs_jax.errors import UserError
from cusgs_jax.eval.features import evaluate_features
from cusgs_jax.eval.views import evaluate_views, nearest_train_view
from cusgs_jax.model.anchors import compact
from cusgs_jax.run_folder import BANKS_FILE, CURVE_FILE, METRICS_FILE, CheckpointMeta, accept_hydra_record, \
    restore_hydra_record
from cusgs_jax.training import capacity
from cusgs_jax.training.loss_terms import LossTally, weighted_terms
from cusgs_jax.training.render import RgbOfFeatureRender, make_feature_render_fn, make_render_fn, most_work
from cusgs_jax.training.state import TrainState, init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera
from cusgs_jax.view.live import live_view
from cusgs_jax.view.render import ViewCamera, ViewModel, scene_cameras, view_model

log = logging.getLogger("cusgs_jax")


@dataclasses.dataclass
class Loop:
    """The training loop's mutable state, in one place: the numeric state and what the shell counts beside it."""

    state: TrainState
    tx: optax.GradientTransformation  # the optimiser of ``state`` (its groups follow the state's tree)
    steps: StepPrograms  # the step's programs and work capacities (app/programs.py): owned, grown, checkpointed
    tallies: dict[str, Tally]  # {strategy name: what its updates did} (checkpointed)
    views: ViewQueue | None = None  # the batch positions still to train, deferred ones included (app/deferral.py)
    render: capacity.ExactRender | RgbOfFeatureRender | None = None  # the evaluation's RGB render (it grows)
    feature_render: capacity.ExactRender | None = None  # and its feature render (feature models only)
    curve: list[dict] = dataclasses.field(default_factory=list)  # the learning curve (eval_curve.jsonl rows)
    alarmed: set[str] = dataclasses.field(default_factory=set)  # loss terms already warned about (loss_alarms)
    loss_tally: LossTally = dataclasses.field(default_factory=LossTally)  # every loss term summed over the steps
    batch_types: dict | None = None  # the types of every batch of the run (ShapeDtypeStructs), once known

    @property
    def capacities(self) -> capacity.Capacities:
        """The step's work capacities now (:attr:`StepPrograms.capacities`)."""
        return self.steps.capacities

    @capacities.setter
    def capacities(self, value: capacity.Capacities) -> None:  # a resume's restored capacities
        self.steps.capacities = value

    @property
    def recompilations(self) -> int:
        """Capacity growths (anchors, visible slots, tile pairs) that changed the step's program."""
        return self.steps.recompilations

    @recompilations.setter
    def recompilations(self, value: int) -> None:
        self.steps.recompilations = value

    @property
    def replays(self) -> int:
        """Steps run again with grown capacities (at once, or later when deferred)."""
        return self.steps.replays

    @replays.setter
    def replays(self, value: int) -> None:
        self.steps.replays = value

    @property
    def programs(self) -> dict:
        """{Capacities: the step's Program for them}."""
        return self.steps.programs


def start(session: Session) -> Loop:
    """The loop a run of ``session`` starts with: a fresh state, or the newest checkpoint's (``train.resume``).

    Accepts the folder's Hydra record (:func:`~cusgs_jax.run_folder.accept_hydra_record`) once the run is
    accepted; a refused resume (another scene, past the iterations) puts the accepted one back.
    """
    try:
        loop = _start(session)
    except UserError:
        restore_hydra_record(session.out)
        raise
    accept_hydra_record(session.out)
    return loop


def _start(session: Session) -> Loop:
    cfg, scene, budget = session.cfg, session.scene, session.budget
    with budget.stage("init"):
        state, tx = init_train_state(cfg, scene.points, len(session.train_idx), scene.extent, session.strategies,
                                     session.banks)
    with budget.stage("probe"):
        steps = StepPrograms(lambda caps: make_train_step(cfg, tx, session.strategies, caps, session.loss_terms),
                             _fitted_capacities(session, state, fill=growth_forecast(session, state)),
                             cfg.model.n_offsets, session.ahead)
        loop = Loop(state=state, tx=tx, steps=steps, tallies={s.name: Tally() for s in session.strategies})
    if cfg.train.resume:
        with budget.stage("checkpoints"):
            resume(session, loop)
    # The evaluation renders the padded model at the step's capacities with headroom (its own grow, should a
    # held-out view need more): one program per anchor capacity; with features one program for RGB and features.
    wrap = functools.partial(Program, ahead=session.ahead)  # its programs can be compiled ahead
    evaluation = loop.capacities.for_evaluation()
    if cfg.features.enabled:
        loop.feature_render = make_feature_render_fn(cfg, evaluation, wrap=wrap)
        loop.render = RgbOfFeatureRender(loop.feature_render, session.banks)
    else:
        loop.render = make_render_fn(cfg, evaluation, wrap=wrap)
    if loop.views is None:
        loop.views = ViewQueue(next=int(loop.state.step), total=cfg.train.iterations)
    # the programs the loop starts with, compiled in the background from here on
    loop.steps.prepare(loop.capacities, loop.state, session.batches(loop.views.next))
    _prepare_render(session, loop, loop.state.anchors)
    return loop


def _compile_ahead(session: Session, loop: Loop, requests) -> None:
    """Hand what the foresight plans (:class:`~cusgs_jax.app.foresight.Request` s) to the programs' owners: the
    step's to :class:`~cusgs_jax.app.programs.StepPrograms`, the evaluation render's to its render."""
    if not requests:
        return
    batch = loop.batch_types if loop.batch_types is not None else session.batches(0)  # one type for every batch
    for request in requests:
        if loop.steps.prepare(request.capacities, request.state, batch):
            log.debug("compiling ahead the step for %d anchor slots, %s", request.state.anchors.capacity,
                      request.capacities)
        if request.render:
            _prepare_render(session, loop, request.state.anchors)


def _prepare_render(session: Session, loop: Loop, anchors) -> None:
    """Compile the evaluation render for ``anchors``' capacity in the background (``anchors``: arrays or
    ``ShapeDtypeStruct`` s of the padded model), so a held-out evaluation does not wait for it."""
    render = loop.feature_render or loop.render
    scene, view = session.scene, int(session.test_idx[0])
    args = (anchors, loop.state.nets, Camera.of_scene(scene, view),
            nearest_train_view(scene.camera_centers, scene.train_indices, view))
    render.program().prepare(*args, *((session.banks,) if loop.feature_render else ()))


def growth_forecast(session: Session, state: TrainState, backend: str | None = None) -> float:
    """How much the start's fit scales the probed views' need (:meth:`~cusgs_jax.training.capacity.Capacities.fitted`'s
    ``fill``): on an accelerator, where a wider step costs little and a step compile much, the growth the
    strategies forecast when one of them grows the alive anchors into the capacity
    (:func:`~cusgs_jax.training.capacity.growth_fill`), so the replays a growth would bring do not happen; on a CPU,
    where every slot costs step time and a grown program compiles in the background while the loop trains around
    it, 1 (what the views need now)."""
    backend = jax.default_backend() if backend is None else backend
    if backend == "cpu" or not _will_grow(session.strategies, session.cfg.train.iterations):
        return 1.0
    return capacity.growth_fill(int(np.sum(np.asarray(state.anchors.alive))), state.anchors.capacity)


def _will_grow(strategies, iterations: int) -> bool:
    """Whether an update of ``strategies`` within ``iterations`` steps may add anchors (one that does more than
    remove them: :meth:`~cusgs_jax.densify.base.Strategy.only_removes`)."""
    return any(strategy.due(step) and not only_removes(strategy, step)
               for strategy in strategies for step in range(1, iterations + 1))


def _fitted_capacities(session: Session, state: TrainState, probes: int = 8, fill: float = 1.0) -> capacity.Capacities:
    """The step's first work capacities, sized by what up to ``probes`` training views (spread over
    them) need of the initial model, times ``fill`` (:func:`growth_forecast`), with headroom
    (:meth:`~cusgs_jax.training.capacity.Capacities.fitted`); the config's guesses are not used. They grow, and the
    step replays, when a later view needs more."""
    scene, cfg = session.scene, session.cfg
    positions = spread(np.arange(len(session.train_idx)), probes)
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
    fitted = capacity.Capacities.fitted(needs, state.anchors.capacity, cfg.model.n_offsets, fill=fill)
    log.info("work capacities from %d probed views (at most %d visible anchors, %d active Gaussians, %d tile "
             "pairs%s): %s", len(positions), needs["visible_anchors"], needs["active_gaussians"],
             needs["pairs"], f"; the strategies' growth forecast: x{fill:.2f}" if fill > 1 else "", fitted)
    return fitted


# --- the loop -------------------------------------------------------------------------------


def train(session: Session, loop: Loop, progress_label: str = "train", foresight: Foresight | None = None) -> None:
    """Steps from the state's step to ``train.iterations``: update, densify, log, evaluate, checkpoint.

    Each update trains one batch (:func:`next_update`): the next fresh one, or one deferred earlier whose program
    is now ready — the loop does not wait for a program compiling in the background while it has views that fit
    the one it has (:mod:`cusgs_jax.app.deferral`). ``foresight``: what plans the programs compiled ahead (default
    :class:`~cusgs_jax.app.foresight.Foresight` of the session's strategies)."""
    cfg = session.cfg
    iterations, start = cfg.train.iterations, int(loop.state.step)
    batches = session.batches
    cameras = scene_cameras(session.scene, session.train_idx) if cfg.train.viewer else []  # fixed during a run
    snapshot = functools.partial(_snapshot, session, loop, cameras)  # the live viewer's model as it is when called
    bar = tqdm(range(start, iterations), initial=start, total=iterations, desc=progress_label,
               disable=not cfg.train.progress, dynamic_ncols=True)
    last_log = time.perf_counter()
    foresight = foresight or Foresight(session.strategies, iterations)
    with session.budget.stage("train_steps"):  # the first step's program, compiled during setup: waited for here
        loop.steps.program().wait(loop.state, batches(loop.views.next))
        if session.ahead is not None:
            session.ahead.loop_starts()
    with open(session.out / METRICS_FILE, "a") as metrics_file, \
            open(session.out / CURVE_FILE, "a") as curve_file, live_view(cfg.train, snapshot) as live:
        for step in bar:
            with session.budget.clock:
                with session.budget.stage("train_steps"):
                    started = time.perf_counter()
                    metrics = next_update(session, loop, step)
                    foresight.stepped(time.perf_counter() - started, metrics)
                with session.budget.stage("densify"):
                    run_strategies(session, loop, step + 1)
                    _compile_ahead(session, loop, foresight.after(session, loop, step + 1))
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
                    point = curve_point(session, loop, done)
                curve_file.write(json.dumps(point) + "\n")
                curve_file.flush()
                bar.write(f"step {done}: {session.psnr_label} {point['psnr']:.2f} dB at {point['wall_s']:.0f} s")
            if cfg.train.checkpoint_every and done % cfg.train.checkpoint_every == 0 and done < iterations:
                with session.budget.stage("checkpoints"):
                    save_checkpoint(session, loop, done)
            signum = interrupt.requested()
            if signum is not None and done < iterations:
                _stop(session, loop, done, signum)
    bar.close()
    if session.ckpt.latest_step() != iterations:  # a resumed run that was already complete has it
        with session.budget.stage("checkpoints"):
            save_checkpoint(session, loop, iterations)


def _stop(session: Session, loop: Loop, done: int, signum: int) -> None:
    """Stop for a signal after ``done`` steps (:mod:`cusgs_jax.app.interrupt`): SIGTERM checkpoints this step first
    (a preempted or timed-out job resumes from it); Ctrl-C stops at once (the newest checkpoint resumes)."""
    checkpoint = None
    if signum == interrupt.signal.SIGTERM:
        if session.ckpt.latest_step() != done:
            save_checkpoint(session, loop, done)
        checkpoint = str(session.ckpt.directory)
    raise interrupt.Interrupted(signum, done, checkpoint)


def _snapshot(session: Session, loop: Loop, cameras: list[ViewCamera]) -> ViewModel:
    """What the live viewer shows of the model as it is now (anchors compacted now).

    The snapshot owns its arrays: the step donates the state's buffers, so the networks are copied
    (small MLPs) rather than shared, and the snapshot stays valid after the next step.
    """
    nets = jax.tree_util.tree_map(jnp.copy, loop.state.nets)
    return view_model(session.cfg, compact(loop.state.anchors), nets, session.banks, cameras)


def exact_step(session: Session, loop: Loop, batch: dict) -> dict:
    """One training step on ``batch`` that dropped no work; returns its metrics (host values).

    A step that reported dropped anchors or tile pairs changed nothing; the capacity is grown
    (:meth:`cusgs_jax.app.programs.StepPrograms.grow`) and the same batch replayed — waiting for the grown
    program's compile if it is under way (:func:`next_update` trains other views meanwhile instead).
    """
    metrics = _step_batch(session, loop, batch)
    assert metrics is not None
    return metrics


def _step_batch(session: Session, loop: Loop, batch: dict, position: int | None = None,
                updates: int = 0) -> dict | None:
    """Train ``batch``, replaying it with grown capacities while it drops work; returns its metrics.

    With a queue position (:func:`next_update`) a batch whose grown program is not ready is deferred instead
    (None is returned): the grown capacities are the union of what it needs and what every deferred batch waits
    for, so the step's capacities only ever grow to ones that hold every batch waiting (no batch is pushed back
    by another's growth)."""
    steps, queue = loop.steps, loop.views
    while True:
        loop.state, metrics = steps(loop.state, batch)
        metrics = jax.device_get(metrics)  # also charges the step's real compute time to the clock
        if not (metrics["dropped_anchors"] or metrics["dropped_gaussians"] or metrics["dropped_pairs"]):
            metrics["terms"] = weighted_terms(metrics, session.weights)
            loop.loss_tally.add(metrics["terms"])
            return metrics
        anchor_capacity = loop.state.anchors.capacity
        if position is None:
            steps.grow(metrics, anchor_capacity)
            continue
        target = functools.reduce(capacity.Capacities.union, queue.capacities(),
                                  steps.grown(metrics, anchor_capacity, announce=False))
        if steps.ready(target, loop.state, batch):  # compiled (ahead, or nothing compiles ahead): replay now
            steps.grown(metrics, anchor_capacity)  # logs the growth
            steps.replay(target)
            continue
        if steps.prepare(target, loop.state, batch):
            log.info("step %d: a view needs more work capacity than the step has (%s): it waits for the step "
                     "for %s, compiling in the background, while the loop trains the views that fit",
                     updates, _shortfall_text(metrics), target)
        queue.defer(position, target, updates)
        return None


def next_update(session: Session, loop: Loop, updates: int) -> dict:
    """One update of :func:`train` after ``updates`` updates; returns its metrics (host values).

    The batch is the oldest deferred one whose program is ready, else the next fresh one
    (:class:`~cusgs_jax.app.deferral.ViewQueue`). A batch that needs grown capacities whose program is still
    compiling in the background is deferred, and the next fresh batch tried with the program the step has; when
    none is left, too many are deferred, or :data:`~cusgs_jax.app.deferral.MAX_TRIES` fresh ones overflowed for
    this update, the loop waits for the oldest deferred one's program (logged, and counted in ``eval.json``'s
    ``deferred``). With every program ready in time this trains the batches in order, as :func:`exact_step` does.
    """
    queue, steps = loop.views, loop.steps
    defer = session.cfg.train.defer_views  # false: wait for a late program (numbers independent of timing)
    if loop.batch_types is None:  # every batch of a run has the same types
        loop.batch_types = ahead_specs(session.batches(queue.next if queue.fresh_left() else queue.waiting[0].position))
    batch_types, tries = loop.batch_types, 0

    def is_ready(capacities) -> bool:
        return steps.covers(capacities) or steps.ready(capacities, loop.state, batch_types)

    while True:
        item = queue.take_ready(is_ready)
        if item is None and queue.must_wait(tries):
            item = queue.take_oldest()
            if item.capacities is not None and not steps.covers(item.capacities):
                started = time.perf_counter()
                log.info("step %d: waiting for the step's program for %s (%d views deferred, %s)", updates,
                         item.capacities, len(queue.waiting) + 1,
                         "no fresh view left" if not queue.fresh_left() else "nearly every view overflows")
                steps.program(item.capacities).wait(loop.state, batch_types)
                queue.waited(time.perf_counter() - started)
        if item is not None:
            steps.replay(item.capacities)  # a union: what the step had and what the view needs
            metrics = _step_batch(session, loop, session.batches(item.position), item.position if defer else None,
                                  updates)
            if metrics is not None:
                queue.trained(item, updates)
                return metrics
            continue
        if not queue.fresh_left():
            raise RuntimeError(f"no batch left to train after {updates} updates")  # cannot happen: T positions
        position = queue.take_fresh()
        metrics = _step_batch(session, loop, session.batches(position), position if defer else None, updates)
        if metrics is not None:
            return metrics
        tries += 1


def _shortfall_text(metrics: dict) -> str:
    """What a step that dropped work lacked, in words (its first overflowing capacity)."""
    for dropped, have, what in (("dropped_anchors", "visible_anchors", "visible anchors"),
                                ("dropped_gaussians", "active_gaussians", "active Gaussians"),
                                ("dropped_pairs", "pairs", "tile pairs")):
        if metrics.get(dropped, 0) > 0:
            return f"{int(metrics[have]) + int(metrics[dropped])} {what} against {int(metrics[have])}"
    return "nothing dropped"


def run_strategies(session: Session, loop: Loop, step: int) -> None:
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
        before = loop.state.anchors.capacity
        loop.state, info = strategy.update(loop.state, loop.tx, step)
        if info.capacity_changed:  # new shapes: the step compiles again (for work capacities that follow A)
            loop.steps.regrow(before, loop.state.anchors.capacity)
            if loop.views is not None:
                loop.views.reset_capacities()
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
    loop.state = ops.resize_capacity(loop.state, loop.tx, new)
    loop.steps.refit(_fitted_capacities(session, loop.state))
    if loop.views is not None:
        loop.views.reset_capacities()
    log.info("step %d: %d of %d anchor slots alive: capacity shrunk to %d (the step recompiles once)",
             step, alive, old, new)


def _probe(session: Session, loop: Loop, step: int) -> Probe:
    """What a strategy's ``before_first_update`` hook may measure of the run after ``step`` steps."""
    def render_ms_per_view() -> float:
        with session.budget.clock.paused(), session.budget.stage("evaluation"):
            return evaluate_model(session, loop, loop.state.anchors, time_renders=True)["render_ms_per_view"]

    return Probe(step=step, render_ms_per_view=render_ms_per_view)


def _log_row(session: Session, loop: Loop, step: int, metrics: dict, step_s: float) -> dict:
    state = loop.state
    row = dict(step=step, wall_s=round(session.budget.clock.total, 3), loss=float(metrics["loss"]),
               **({"feature_loss": float(metrics["loss_feature"])} if session.banks is not None else {}),
               terms={name: round(float(value), 7) for name, value in metrics.get("terms", {}).items()},
               train_psnr=float(metrics["psnr"]), alive_anchors=int(np.sum(np.asarray(state.anchors.alive))),
               visible_anchors=int(metrics["visible_anchors"]), active_gaussians=int(metrics["active_gaussians"]),
               pairs=int(metrics["pairs"]), **strategy_row(session.strategies, loop.tallies, session.cfg),
               skipped=int(state.skipped), dropped_anchors=int(metrics["dropped_anchors"]),
               dropped_gaussians=int(metrics["dropped_gaussians"]),
               dropped_pairs=int(metrics["dropped_pairs"]), replays=loop.replays,
               recompilations=loop.recompilations, step_s=round(step_s, 4))
    loss_alarms(loop.alarmed, step, metrics)
    return row


def evaluate_model(session: Session, loop: Loop, anchors, **kwargs) -> dict:
    """Held-out PSNR/SSIM of the model as it is now; ``anchors`` = ``loop.state.anchors`` (padded, alive mask)."""
    return evaluate_views(loop.render, anchors, loop.state.nets, session.scene, session.test_idx, **kwargs)


def evaluate_model_features(session: Session, loop: Loop, anchors, **kwargs) -> dict:
    """Feature errors of the model as it is now; ``anchors`` = ``loop.state.anchors`` (padded, alive mask)."""
    return evaluate_features(loop.feature_render, anchors, loop.state.nets, session.scene, session.test_idx,
                             session.banks, session.feature_sets, **kwargs)


def curve_point(session: Session, loop: Loop, step: int) -> dict:
    anchors = loop.state.anchors  # padded, with its alive mask: the shapes the step has (no new program)
    result = evaluate_model(session, loop, anchors)
    point = dict(step=step, wall_s=session.budget.clock.total, psnr=result["psnr"], ssim=result["ssim"],
                 alive_anchors=int(np.sum(np.asarray(loop.state.anchors.alive))))
    if session.banks is not None:
        feats = evaluate_model_features(session, loop, anchors, retrieval=False)["models"]
        point["feature_cosine"] = float(np.mean([m["cosine"] for m in feats.values()]))
        point["feature_l2"] = float(np.mean([m["l2"] for m in feats.values()]))
    loop.curve.append(point)
    return point


def save_checkpoint(session: Session, loop: Loop, step: int) -> None:
    meta = CheckpointMeta(
        step=step, capacity=loop.state.anchors.capacity, wall_s=session.budget.clock.total, curve=loop.curve,
        densify={name: tally.as_dict() for name, tally in loop.tallies.items()},
        recompilations=loop.recompilations, replays=loop.replays, loss_terms=loop.loss_tally.as_dict(),
        views=None if loop.views is None else loop.views.as_dict(),
        capacities=loop.capacities.as_dict(), voxel_size=session.cfg.model.voxel_size,
        # what cusgs-export needs from an unfinished run or one trained without Hydra (io/load_run.py)
        world_transform=session.world.as_dict(), config=dataclasses.asdict(session.cfg),
        train_cameras=session.cameras(session.train_idx), scene_digest=session.digest(),
        held_out_cameras=session.cameras(session.scene.test_indices))  # cusgs-view's camera list
    session.ckpt.save(step, loop.state, meta.to_json())
    if session.banks is not None and not (session.out / BANKS_FILE).is_file():  # what cusgs-view renders with
        np.savez(session.out / BANKS_FILE, **{name: np.asarray(b) for name, b in session.banks.items()})


