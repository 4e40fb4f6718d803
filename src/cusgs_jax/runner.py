"""The training run (imperative shell): data → state → loop → checkpoints → evaluation.

``run(cfg, output_dir)`` takes a plain nested dict (what Hydra composes) and
writes into ``output_dir``:

* ``metrics.jsonl`` — step, wall seconds, loss, train PSNR, alive anchors, …
* ``eval_curve.jsonl`` — held-out PSNR (and feature errors) every ``eval.every`` steps with wall seconds
* ``eval.json`` — per-view and mean PSNR/SSIM, model size, times, pruning summary
* ``renders/`` — held-out renders beside ground truth (PNG)
* ``error_vs_time.png`` — held-out PSNR against training wall-clock time
* ``checkpoints/`` — orbax checkpoints (periodic and final)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cusgs_jax.checkpoint import Checkpointer
from cusgs_jax.feature_field import FeatureConfig, FeatureModelConfig, refill_query_table
from cusgs_jax.evaluate import count_parameters, evaluate_views
from cusgs_jax.grow_prune import GrowConfig, adjust_anchors
from cusgs_jax.optim import OptimConfig, make_optimizer, reset_rows
from cusgs_jax.prune import PruneConfig, prune_due
from cusgs_jax.report import plot_error_vs_time
from cusgs_jax.scaffold import grow_capacity
from cusgs_jax.train import (LossConfig, ModelConfig, SplatConfig, TrainConfig, TrainState, compact_for_render,
                             init_train_state, make_feature_render_fn, make_prune_step, make_render_fn,
                             make_train_step, render_config)

log = logging.getLogger("cusgs_jax")


def _build(cls, values: dict | None):
    values = dict(values or {})
    kwargs = {}
    for field in dataclasses.fields(cls):
        if field.name not in values:
            continue
        value = values.pop(field.name)
        kwargs[field.name] = tuple(value) if isinstance(value, list) else value
    if values:
        raise ValueError(f"unknown {cls.__name__} option(s): {sorted(values)}; "
                         f"valid: {[f.name for f in dataclasses.fields(cls)]}")
    return cls(**kwargs)


DEMO_FEATURE_MODELS = ({"name": "daisy", "query_dim": 16, "gamma": 0.8},
                       {"name": "semantic", "query_dim": 16, "gamma": 1.0})


def feature_config(values: dict | None, granularity: str = "per_anchor", demo: bool = False) -> FeatureConfig:
    """FeatureConfig from ``features.*``; ``models: auto`` means the demo's two models on the
    built-in demo scene and none on a user's scene."""
    values = dict(values or {})
    models = values.pop("models", None) or ()
    if models == "auto":
        models = DEMO_FEATURE_MODELS if demo else ()
    models = tuple(_build(FeatureModelConfig, m) for m in models)
    return dataclasses.replace(_build(FeatureConfig, values), models=models, granularity=granularity)


def train_config(cfg: dict) -> TrainConfig:
    """Static :class:`TrainConfig` from the composed config dict."""
    model = cfg.get("model") or {}
    return TrainConfig(
        features=feature_config(cfg.get("features"), model.get("query_granularity", "per_anchor"),
                                demo=not (cfg.get("data") or {}).get("path")),
        iterations=int(cfg["train"]["iterations"]), seed=int(cfg["train"]["seed"]),
        model=_build(ModelConfig, cfg.get("model")), splat=_build(SplatConfig, cfg.get("splat")),
        loss=_build(LossConfig, cfg.get("loss")), optim=_build(OptimConfig, cfg.get("optim")),
        grow=_build(GrowConfig, cfg.get("grow")), prune=_build(PruneConfig, cfg.get("prune")),
    )


def load_data(cfg: dict):
    """SceneData from ``data.path``, or the built-in demo scene when it is null."""
    from cusgs_jax.data.colmap import load_scene

    data = cfg["data"]
    path = data.get("path")
    if not path:
        from cusgs_jax.data.demo import demo_scene_path

        demo = data.get("demo") or {}
        path = demo_scene_path(seed=int(demo.get("seed", 0)), num_views=int(demo.get("views", 30)),
                               width=int(demo.get("width", 160)), height=int(demo.get("height", 120)))
        log.info("using the built-in demo scene at %s", path)
    return load_scene(path, downscale=int(data.get("downscale", 1)),
                      holdout_every=int(data.get("holdout_every", 8)))


BUILT_IN_EXTRACTORS = ("daisy", "hog", "gabor", "semantic")


def load_feature_targets(fcfg: FeatureConfig, scene, seed: int, auto_extract: bool):
    """Feature maps of every configured model and their PSC banks.

    Missing built-in features are extracted first when ``auto_extract`` (the
    demo scene's default). The PSC scan sees a seeded random subset of the
    training pixels (``psc_rows``) in random order, so the ``max_bank_entries``
    cap samples the whole scene rather than its first views.

    Returns:
      (maps {model: FeatureSet}, banks {model: [S, D] float32 numpy}).
    """
    from cusgs_jax.data.features import load_features
    from cusgs_jax.memory import psc

    maps, banks = {}, {}
    for index, model in enumerate(fcfg.models):
        if auto_extract and model.name in BUILT_IN_EXTRACTORS:
            from cusgs_jax.extract import ensure_extracted

            # locked: the jobs of a parallel sweep share the demo scene's cache
            if ensure_extracted(scene.path, model.name, progress=False):
                log.info("extracted %s features for %s", model.name, scene.path)
        fs = load_features(scene.path, model.name, scene.names, image_size=(scene.width, scene.height))
        rows = fs.maps[scene.train_indices].reshape(-1, fs.dim)
        rows = rows[np.any(rows != 0, axis=-1)]
        rng = np.random.default_rng([seed, 7, index])
        rows = rows[rng.permutation(len(rows))[: fcfg.psc_rows]]
        bank = psc.build(rows, model.gamma, max_entries=fcfg.max_bank_entries)
        if bank.count == 0:
            raise ValueError(f"feature model {model.name!r}: no non-zero training targets to build a memory from")
        log.info("PSC %s: %d entries from %d pixels (gamma %.2f)", model.name, bank.count, len(rows), model.gamma)
        maps[model.name], banks[model.name] = fs, np.asarray(bank.entries, np.float32)
    return maps, banks


def view_order(seed: int, num_train: int, step: int) -> int:
    """Training view (position in the train list) used at ``step``.

    A fresh permutation per epoch, derived from (seed, epoch) alone, so a
    resumed run sees exactly the same sequence.
    """
    epoch, position = divmod(step, num_train)
    return int(np.random.default_rng([seed, epoch]).permutation(num_train)[position])


def _template_state(tcfg: TrainConfig, scene, capacity: int, banks=None):
    """A state of the right structure and shapes for restoring a checkpoint."""
    state, _ = init_train_state(tcfg, scene.points, len(scene.train_indices), scene.extent, banks)
    if state.anchors.capacity != capacity:
        old = state.anchors.capacity
        if capacity > old:
            state = grow_capacity(state, old, capacity)
        else:
            state = jax.tree_util.tree_map(
                lambda x: x[:capacity] if hasattr(x, "shape") and x.ndim and x.shape[0] == old else x, state)
    return state


class _Clock:
    """Training wall-clock time, excluding evaluation and checkpointing."""

    def __init__(self, offset: float = 0.0):
        self.total = offset
        self._start = None

    def __enter__(self):
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.total += time.perf_counter() - self._start

    @contextlib.contextmanager
    def paused(self):
        """Inside a ``with clock:`` block: the time spent here is not charged."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self._start += time.perf_counter() - start


def run(cfg: dict, output_dir: str | pathlib.Path, progress_label: str = "train") -> dict:
    """Train, checkpoint and evaluate; returns the final ``eval.json`` dict.

    ``progress_label`` names the progress bar (a sweep labels each job's bar).
    """
    out = pathlib.Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    train_cfg, eval_cfg = cfg["train"], cfg.get("eval", {})
    tcfg = train_config(cfg)
    scene = load_data(cfg)
    width, height = scene.width, scene.height
    train_idx = scene.train_indices
    test_idx = scene.test_indices if len(scene.test_indices) else scene.train_indices[:1]
    log.info("scene %s: %d train / %d held-out views at %dx%d, %d points, extent %.3f",
             scene.path, len(train_idx), len(scene.test_indices), width, height, len(scene.points), scene.extent)

    images = jnp.asarray(scene.images[train_idx].astype(np.float32) / 255.0)
    viewmats = jnp.asarray(scene.viewmats[train_idx])
    Ks = jnp.asarray(scene.Ks[train_idx])

    fcfg = tcfg.features
    feature_sets, banks, targets = {}, None, {}
    if fcfg.enabled:
        feature_sets, banks = load_feature_targets(fcfg, scene, tcfg.seed,
                                                   fcfg.auto_extract)
        targets = {name: jnp.asarray(fs.maps[train_idx].astype(np.float16)) for name, fs in feature_sets.items()}
        banks = {name: jnp.asarray(b) for name, b in banks.items()}
    state, tx = init_train_state(tcfg, scene.points, len(train_idx), scene.extent, banks)
    ckpt = Checkpointer(train_cfg.get("checkpoint_dir") or out / "checkpoints")
    clock = _Clock()
    curve: list[dict] = []
    if train_cfg.get("resume") and ckpt.latest_step() is not None:
        meta = ckpt.metadata()
        state, meta = ckpt.restore(_template_state(tcfg, scene, int(meta["capacity"]), banks))
        tx = make_optimizer(tcfg.optim, state.params, tcfg.iterations, scene.extent)
        clock = _Clock(float(meta["wall_s"]))
        curve = list(meta["curve"])
        log.info("resumed from step %d (capacity %d)", int(state.step), state.anchors.capacity)
    step_fn = make_train_step(tcfg, tx, width, height)
    render = make_render_fn(tcfg, width, height)

    grow, pcfg = tcfg.grow, tcfg.prune
    prune_fn = make_prune_step(tcfg)
    render_cfg = render_config(tcfg)
    compact_render = make_render_fn(render_cfg, width, height)
    feature_render = make_feature_render_fn(tcfg, width, height) if fcfg.enabled else None
    render_before_prune, prune_passes, pruned_total = None, 0, 0
    if train_cfg.get("resume") and ckpt.latest_step() is not None:
        prune_meta = ckpt.metadata().get("prune", {})
        render_before_prune = prune_meta.get("render_ms_before_prune")
        prune_passes, pruned_total = int(prune_meta.get("passes", 0)), int(prune_meta.get("pruned", 0))

    def compacted(state):
        return compact_for_render(state.params, state.anchors)

    def time_render(state):
        """Median ms per held-out view of the model as it is now, dead slots dropped."""
        params, anchors = compacted(state)
        return evaluate_views(compact_render, params, anchors, scene, test_idx, time_renders=True)[
            "render_ms_per_view"]

    iterations = tcfg.iterations
    eval_every = int(eval_cfg.get("every", 500))
    ckpt_every = int(train_cfg.get("checkpoint_every", 1000))
    log_every = int(train_cfg.get("log_every", 10))
    metrics_file = open(out / "metrics.jsonl", "a")
    curve_file = open(out / "eval_curve.jsonl", "a")
    start_step = int(state.step)

    def save(step):
        meta = dict(step=step, capacity=state.anchors.capacity, wall_s=clock.total, curve=curve,
                    prune=dict(passes=prune_passes, pruned=pruned_total, render_ms_before_prune=render_before_prune))
        ckpt.save(step, state, meta)

    def evaluate_curve(step):
        result = evaluate_views(render, state.params, state.anchors, scene, test_idx)
        point = dict(step=step, wall_s=clock.total, psnr=result["psnr"], ssim=result["ssim"],
                     alive_anchors=int(np.sum(state.anchors.alive)))
        if fcfg.enabled:
            from cusgs_jax.evaluate import evaluate_features

            feats = evaluate_features(feature_render, state.params, state.anchors, scene, test_idx, banks,
                                      feature_sets, retrieval=False)["models"]
            point["feature_cosine"] = float(np.mean([m["cosine"] for m in feats.values()]))
            point["feature_l2"] = float(np.mean([m["l2"] for m in feats.values()]))
        curve.append(point)
        curve_file.write(json.dumps(point) + "\n")
        curve_file.flush()
        return point

    bar = tqdm(range(start_step, iterations), initial=start_step, total=iterations, desc=progress_label,
               disable=not train_cfg.get("progress", True), dynamic_ncols=True)
    last_log = time.perf_counter()
    for step in bar:
        view = view_order(tcfg.seed, len(train_idx), step)
        batch = dict(image=images[view], viewmat=viewmats[view], K=Ks[view], index=jnp.int32(view))
        if fcfg.enabled:
            batch["features"] = {name: t[view] for name, t in targets.items()}
            batch["banks"] = banks
        with clock:
            state, metrics = step_fn(state, batch)
            jax.block_until_ready(metrics)  # charge the step's real compute time to the clock
            if grow.start <= step + 1 <= grow.stop and (step + 1) % grow.interval == 0:
                old_alive = np.asarray(state.anchors.alive)
                anchor_params, anchors, stats, opt_state, info = adjust_anchors(
                    state.params["anchor"], state.anchors, state.stats, state.opt_state, grow,
                    tcfg.model.voxel_size, np.random.default_rng([tcfg.seed, step]))
                params = dict(state.params, anchor=anchor_params)
                if info["capacity_grew"]:
                    # adjust_anchors padded the anchor arrays and the optimiser state; other
                    # capacity-shaped parameters (the per-Gaussian query table) grow here too.
                    # The step recompiles once.
                    params = grow_capacity(params, info["capacity_grew"], info["capacity"])
                    log.warning("anchor capacity full: grew %d -> %d slots (the step recompiles once)",
                                info["capacity_grew"], info["capacity"])
                prune_stats = state.prune
                if info["capacity_grew"]:
                    prune_stats = grow_capacity(prune_stats, info["capacity_grew"], info["capacity"])
                    old_alive = np.pad(old_alive, (0, info["capacity"] - len(old_alive)))
                # slots refilled by growing start their pruning statistics (and per-Gaussian queries) afresh
                refilled = jnp.asarray(np.asarray(anchors.alive) & ~old_alive)
                prune_stats = prune_stats.clear(refilled)
                if "table" in params.get("queries", {}):
                    key = jax.random.fold_in(jax.random.PRNGKey(tcfg.seed), step)
                    params["queries"] = dict(params["queries"], table=refill_query_table(
                        params["queries"]["table"], refilled, key))
                    opt_state = reset_rows(opt_state, refilled, info["capacity"], group="table")
                state = TrainState(params=params, opt_state=opt_state, anchors=anchors, stats=stats,
                                   prune=prune_stats, step=state.step, skipped=state.skipped)
            if prune_due(step + 1, pcfg):
                if render_before_prune is None:
                    with clock.paused():
                        render_before_prune = time_render(state)
                state, info = prune_fn(state)
                prune_passes += 1
                pruned_total += int(info["pruned"])
        if (step + 1) % log_every == 0 or step + 1 == iterations:
            metrics = jax.device_get(metrics)
            now = time.perf_counter()
            row = dict(step=step + 1, wall_s=round(clock.total, 3), loss=float(metrics["loss"]),
                       **({"feature_loss": float(metrics["loss_feature"])} if fcfg.enabled else {}),
                       train_psnr=float(metrics["psnr"]), alive_anchors=int(np.sum(state.anchors.alive)),
                       visible_anchors=int(metrics["visible_anchors"]), pruned=pruned_total,
                       skipped=int(state.skipped),
                       visible_overflow=int(metrics["visible_overflow"]),
                       overflow=int(metrics["overflow"]),
                       step_s=round((now - last_log) / log_every, 4))
            last_log = now
            if row["visible_overflow"] or row["overflow"]:
                log.warning("step %d: %d visible anchors did not fit model.visible_fraction and %d tile pairs "
                            "overflowed splat.max_pairs_per_gaussian; raise them if this persists",
                            step + 1, row["visible_overflow"], row["overflow"])
            metrics_file.write(json.dumps(row) + "\n")
            metrics_file.flush()
            bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['train_psnr']:.2f}",
                            anchors=row["alive_anchors"], step_s=row["step_s"])
        if eval_every and ((step + 1) % eval_every == 0 or step + 1 == iterations):
            point = evaluate_curve(step + 1)
            bar.write(f"step {step + 1}: held-out PSNR {point['psnr']:.2f} dB at {point['wall_s']:.0f} s")
        if ckpt_every and (step + 1) % ckpt_every == 0 and step + 1 < iterations:
            save(step + 1)
    bar.close()
    save(iterations)
    metrics_file.close()
    curve_file.close()

    # Final evaluation on the compacted model: dead (pruned) slots are dropped,
    # so render time reflects the alive anchors only (train.compact_for_render).
    final_params, final_anchors = compacted(state)
    final = evaluate_views(compact_render, final_params, final_anchors, scene, test_idx,
                           out_dir=out / "renders" if eval_cfg.get("save_renders", True) else None,
                           time_renders=True)
    size = count_parameters(state.params, np.asarray(state.anchors.alive), banks)
    result = dict(
        psnr=final["psnr"], ssim=final["ssim"], per_view=final["per_view"],
        params=size, alive_anchors=int(np.sum(state.anchors.alive)), capacity=state.anchors.capacity,
        checkpoint_bytes=ckpt.step_bytes(iterations), train_wall_s=clock.total,
        render_ms_per_view=final["render_ms_per_view"], render_ms_before_prune=render_before_prune,
        prune=dict(strategy=pcfg.strategy, ratio=pcfg.ratio, lambda_norm=pcfg.lambda_norm,
                   lambda_grad=pcfg.lambda_grad, passes=prune_passes, pruned=pruned_total),
        skipped_updates=int(state.skipped),
        iterations=iterations, width=width, height=height, held_out_views=len(test_idx),
        curve=curve,
    )
    if fcfg.enabled:
        from cusgs_jax.evaluate import evaluate_features

        result["features"] = evaluate_features(
            feature_render, state.params, state.anchors, scene, test_idx, banks,
            feature_sets, out_dir=out / "features" if eval_cfg.get("save_renders", True) else None)
        (out / "features.md").write_text(result["features"]["markdown"])
    (out / "eval.json").write_text(json.dumps(result, indent=1))
    plot_error_vs_time(curve, out / "error_vs_time.png",
                       title=f"held-out PSNR vs time ({pathlib.Path(str(scene.path)).name})")
    ckpt.close()
    log.info("held-out PSNR %.2f dB, SSIM %.4f, %d anchors, %.0f s training", result["psnr"], result["ssim"],
             result["alive_anchors"], result["train_wall_s"])
    return result


__all__ = ["run", "train_config", "load_data", "view_order"]
