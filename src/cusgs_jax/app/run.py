"""The training run (imperative shell): setup → loop → finalise.

``run(cfg, output_dir)`` takes a :class:`cusgs_jax.config.Config` and writes into ``output_dir``:

* ``metrics.jsonl`` — step, wall seconds, loss, train PSNR, alive anchors, …
  (a resumed run first drops the rows after the restored step, so steps stay unique and increasing)
* ``eval_curve.jsonl`` — held-out PSNR (and feature errors) every ``eval.every`` steps with wall seconds
* ``eval.json`` — per-view and mean PSNR/SSIM, model size, times, pruning summary
* ``renders/`` — held-out renders beside ground truth (PNG)
* ``error_vs_time.png`` — held-out PSNR against training wall-clock time
* ``checkpoints/`` — orbax checkpoints (periodic and final)

The learning curve and the final evaluation use the same renderer: the model
compacted to its alive anchors (:func:`cusgs_jax.model.anchors.compact`), every slot decoded.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cusgs_jax.app.clock import Clock
from cusgs_jax.app.inputs import load_data, load_feature_targets, view_order
from cusgs_jax.config import Config
from cusgs_jax.densify import ops
from cusgs_jax.densify.base import make_strategies
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy
from cusgs_jax.eval.views import count_parameters, evaluate_views
from cusgs_jax.model.anchors import compact
from cusgs_jax.training.checkpoint import Checkpointer
from cusgs_jax.training.render import make_feature_render_fn, make_render_fn
from cusgs_jax.training.state import init_train_state
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera

log = logging.getLogger("cusgs_jax")


@dataclasses.dataclass
class Session:
    """Host-side context of one run (mutable; the numeric state is ``state``)."""

    cfg: Config
    out: pathlib.Path
    scene: object
    train_idx: np.ndarray
    test_idx: np.ndarray
    feature_sets: dict
    banks: dict | None
    targets: dict
    strategies: tuple
    tx: object
    state: object
    ckpt: Checkpointer
    clock: Clock
    curve: list
    prune: dict  # {"passes", "pruned", "render_ms_before_prune"}
    recompilations: int = 0
    render: object = None
    feature_render: object = None


# --- setup ----------------------------------------------------------------------------------


def setup(cfg: Config, output_dir) -> Session:
    """Scene, feature targets, fresh (or resumed) state, step and renderers."""
    out = pathlib.Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = dataclasses.replace(cfg, features=cfg.features.resolve(demo_scene=not cfg.data.path))
    scene = load_data(cfg)
    train_idx = scene.train_indices
    test_idx = scene.test_indices if len(scene.test_indices) else scene.train_indices[:1]
    log.info("scene %s: %d train / %d held-out views at %dx%d, %d points, extent %.3f", scene.path, len(train_idx),
             len(scene.test_indices), scene.width, scene.height, len(scene.points), scene.extent)
    feature_sets, banks, targets = {}, None, {}
    if cfg.features.enabled:
        feature_sets, banks = load_feature_targets(cfg.features, scene, cfg.train.seed)
        targets = {name: jnp.asarray(fs.maps[train_idx].astype(np.float16)) for name, fs in feature_sets.items()}
        banks = {name: jnp.asarray(b) for name, b in banks.items()}
    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, scene.points, len(train_idx), scene.extent, strategies, banks)
    session = Session(cfg=cfg, out=out, scene=scene, train_idx=train_idx, test_idx=test_idx,
                      feature_sets=feature_sets, banks=banks, targets=targets, strategies=strategies, tx=tx,
                      state=state, ckpt=Checkpointer(cfg.train.checkpoint_dir or out / "checkpoints"), clock=Clock(),
                      curve=[], prune=dict(passes=0, pruned=0, render_ms_before_prune=None))
    if cfg.train.resume and session.ckpt.latest_step() is not None:
        _resume(session)
    session.render = make_render_fn(cfg)
    session.feature_render = make_feature_render_fn(cfg) if cfg.features.enabled else None
    return session


def _resume(session: Session) -> None:
    """Restore the newest checkpoint (its metadata read once) and trim the logs to its step."""
    template = session.state
    capacity = int(session.ckpt.metadata()["capacity"])
    if capacity != template.anchors.capacity:
        template = ops.grow_capacity(template, session.tx, capacity)
    session.state, meta = session.ckpt.restore(template)
    step = int(session.state.step)
    session.clock = Clock(float(meta["wall_s"]))
    session.curve = list(meta["curve"])
    session.prune = dict(session.prune, **meta.get("prune", {}))
    session.recompilations = int(meta.get("recompilations", 0))
    _trim_jsonl(session.out / "metrics.jsonl", step)
    _trim_jsonl(session.out / "eval_curve.jsonl", step)
    log.info("resumed from step %d (capacity %d)", step, session.state.anchors.capacity)


def _trim_jsonl(path: pathlib.Path, last_step: int) -> None:
    """Keep the rows of ``path`` with ``step ≤ last_step`` (rows written after the checkpoint go)."""
    if not path.is_file():
        return
    rows = [line for line in path.read_text().splitlines() if line.strip()]
    kept = [line for line in rows if json.loads(line)["step"] <= last_step]
    path.write_text("".join(line + "\n" for line in kept))


# --- the loop -------------------------------------------------------------------------------


def train(session: Session, progress_label: str = "train") -> None:
    """Steps from the state's step to ``train.iterations``: update, densify, log, evaluate, checkpoint."""
    cfg = session.cfg
    iterations, start = cfg.train.iterations, int(session.state.step)
    step_fn = make_train_step(cfg, session.tx, session.strategies)
    batches = _batches(session)
    bar = tqdm(range(start, iterations), initial=start, total=iterations, desc=progress_label,
               disable=not cfg.train.progress, dynamic_ncols=True)
    last_log = time.perf_counter()
    with open(session.out / "metrics.jsonl", "a") as metrics_file, \
            open(session.out / "eval_curve.jsonl", "a") as curve_file:
        for step in bar:
            with session.clock:
                session.state, metrics = step_fn(session.state, batches(step))
                jax.block_until_ready(metrics)  # charge the step's real compute time to the clock
                _densify(session, step + 1)
            done = step + 1
            if done % cfg.train.log_every == 0 or done == iterations:
                row = _log_row(session, done, metrics, (time.perf_counter() - last_log) / cfg.train.log_every)
                last_log = time.perf_counter()
                metrics_file.write(json.dumps(row) + "\n")
                metrics_file.flush()
                bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['train_psnr']:.2f}",
                                anchors=row["alive_anchors"], step_s=row["step_s"])
            if cfg.eval.every and (done % cfg.eval.every == 0 or done == iterations):
                point = _curve_point(session, done)
                curve_file.write(json.dumps(point) + "\n")
                curve_file.flush()
                bar.write(f"step {done}: held-out PSNR {point['psnr']:.2f} dB at {point['wall_s']:.0f} s")
            if cfg.train.checkpoint_every and done % cfg.train.checkpoint_every == 0 and done < iterations:
                _save(session, done)
    bar.close()
    _save(session, iterations)


def _batches(session: Session):
    """``batch(step)``: the training view of ``step`` (:func:`view_order`) as the step's input."""
    scene, idx = session.scene, session.train_idx
    images = jnp.asarray(scene.images[idx].astype(np.float32) / 255.0)
    viewmats, Ks = jnp.asarray(scene.viewmats[idx]), jnp.asarray(scene.Ks[idx])

    def batch(step: int) -> dict:
        view = view_order(session.cfg.train.seed, len(idx), step)
        out = dict(image=images[view], camera=Camera(Ks[view], viewmats[view], scene.width, scene.height),
                   index=jnp.int32(view))
        if session.banks is not None:
            out["features"] = {name: t[view] for name, t in session.targets.items()}
            out["banks"] = session.banks
        return out

    return batch


def _densify(session: Session, step: int) -> None:
    """Run every strategy due after ``step`` completed steps (host side, between steps)."""
    for strategy in session.strategies:
        if not strategy.due(step):
            continue
        is_prune = strategy.name == FeaturePruneStrategy.name
        if is_prune and session.prune["render_ms_before_prune"] is None:
            with session.clock.paused():
                session.prune["render_ms_before_prune"] = _evaluate(session, time_renders=True)["render_ms_per_view"]
        session.state, info = strategy.update(session.state, session.tx, step)
        if info.get("capacity_grew"):
            session.recompilations += 1
        if is_prune:
            session.prune["passes"] += 1
            session.prune["pruned"] += int(info["pruned"])


def _log_row(session: Session, step: int, metrics: dict, step_s: float) -> dict:
    metrics = jax.device_get(metrics)
    state = session.state
    row = dict(step=step, wall_s=round(session.clock.total, 3), loss=float(metrics["loss"]),
               **({"feature_loss": float(metrics["loss_feature"])} if session.banks is not None else {}),
               train_psnr=float(metrics["psnr"]), alive_anchors=int(np.sum(state.anchors.alive)),
               visible_anchors=int(metrics["visible_anchors"]), pruned=session.prune["pruned"],
               skipped=int(state.skipped), visible_overflow=int(metrics["visible_overflow"]),
               overflow=int(metrics["overflow"]), step_s=round(step_s, 4))
    if row["visible_overflow"] or row["overflow"]:
        log.warning("step %d: %d visible anchors did not fit model.visible_fraction and %d tile pairs "
                    "overflowed splat.max_pairs_per_gaussian; raise them if this persists",
                    step, row["visible_overflow"], row["overflow"])
    return row


def _evaluate(session: Session, **kwargs) -> dict:
    """Held-out PSNR/SSIM of the model as it is now, compacted to its alive anchors."""
    anchors = compact(session.state.anchors)
    return evaluate_views(session.render, anchors, session.state.nets, session.scene, session.test_idx, **kwargs)


def _evaluate_features(session: Session, **kwargs) -> dict:
    from cusgs_jax.eval.features import evaluate_features

    anchors = compact(session.state.anchors)
    return evaluate_features(session.feature_render, anchors, session.state.nets, session.scene, session.test_idx,
                             session.banks, session.feature_sets, **kwargs)


def _curve_point(session: Session, step: int) -> dict:
    result = _evaluate(session)
    point = dict(step=step, wall_s=session.clock.total, psnr=result["psnr"], ssim=result["ssim"],
                 alive_anchors=int(np.sum(session.state.anchors.alive)))
    if session.banks is not None:
        feats = _evaluate_features(session, retrieval=False)["models"]
        point["feature_cosine"] = float(np.mean([m["cosine"] for m in feats.values()]))
        point["feature_l2"] = float(np.mean([m["l2"] for m in feats.values()]))
    session.curve.append(point)
    return point


def _save(session: Session, step: int) -> None:
    meta = dict(step=step, capacity=session.state.anchors.capacity, wall_s=session.clock.total, curve=session.curve,
                prune=session.prune, recompilations=session.recompilations)
    session.ckpt.save(step, session.state, meta)


# --- finalise -------------------------------------------------------------------------------


def finalise(session: Session) -> dict:
    """Final held-out evaluation, ``eval.json``, plots; returns the ``eval.json`` dict."""
    from cusgs_jax.eval.plots import plot_error_vs_time

    cfg, out, state = session.cfg, session.out, session.state
    save = cfg.eval.save_renders
    final = _evaluate(session, out_dir=out / "renders" if save else None, time_renders=True)
    prune_cfg = cfg.prune
    result = dict(
        psnr=final["psnr"], ssim=final["ssim"], per_view=final["per_view"],
        params=count_parameters(state.anchors, state.nets, session.banks),
        alive_anchors=int(np.sum(state.anchors.alive)), capacity=state.anchors.capacity,
        checkpoint_bytes=session.ckpt.step_bytes(cfg.train.iterations), train_wall_s=session.clock.total,
        render_ms_per_view=final["render_ms_per_view"],
        render_ms_before_prune=session.prune["render_ms_before_prune"],
        prune=dict(strategy=prune_cfg.strategy, ratio=prune_cfg.ratio, lambda_norm=prune_cfg.lambda_norm,
                   lambda_grad=prune_cfg.lambda_grad, passes=session.prune["passes"], pruned=session.prune["pruned"]),
        skipped_updates=int(state.skipped), recompilations=session.recompilations,
        iterations=cfg.train.iterations, width=session.scene.width, height=session.scene.height,
        held_out_views=len(session.test_idx), curve=session.curve,
    )
    if session.banks is not None:
        result["features"] = _evaluate_features(session, out_dir=out / "features" if save else None)
        (out / "features.md").write_text(result["features"]["markdown"])
    (out / "eval.json").write_text(json.dumps(result, indent=1))
    plot_error_vs_time(session.curve, out / "error_vs_time.png",
                       title=f"held-out PSNR vs time ({pathlib.Path(str(session.scene.path)).name})")
    session.ckpt.close()
    log.info("held-out PSNR %.2f dB, SSIM %.4f, %d anchors, %.0f s training", result["psnr"], result["ssim"],
             result["alive_anchors"], result["train_wall_s"])
    return result


def run(cfg: Config, output_dir, progress_label: str = "train") -> dict:
    """Train, checkpoint and evaluate; returns the final ``eval.json`` dict.

    ``progress_label`` names the progress bar (a sweep labels each job's bar).
    """
    session = setup(cfg, output_dir)
    train(session, progress_label)
    return finalise(session)
