"""Render speed and quality of a trained model before and after feature-aware pruning; prints JSON.

Takes a finished run folder (``cusgs-train`` writes ``.hydra/config.yaml`` and
``checkpoints/``), restores the final state and, side by side in one process:

1. accumulates the pruning statistics over every training view once, from the
   trained parameters (the train step is run on a copy and only its
   ``PruneStats`` are kept, so the parameters never change);
2. for each ``--ratios`` value removes ``floor(ratio · alive)`` anchors with
   one :func:`cusgs_jax.prune.prune_pass` (no fine-tuning afterwards), and the
   same number of *randomly chosen* alive anchors as a baseline for the score;
3. renders every held-out view of the compacted model (dead slots dropped,
   ``train.compact_for_render``) and reports PSNR, SSIM and the median ms per
   view, best of ``--repeats`` passes taken round-robin over all models.

Ratio 0 is the unpruned model ("before"). Ratios of render time are the
meaningful numbers; absolute times on a shared machine are noisy.

    python benchmarks/prune_bench.py multirun/voxel_size/<date>/1 [--ratios 0 0.01 0.05 0.1 0.3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from omegaconf import OmegaConf

from cusgs_jax.checkpoint import Checkpointer
from cusgs_jax.evaluate import count_parameters, evaluate_views
from cusgs_jax.optim import make_optimizer
from cusgs_jax.runner import _template_state, load_data, load_feature_targets, train_config, view_order
from cusgs_jax.scaffold import Anchors
from cusgs_jax.train import (compact_for_render, make_prune_step, make_render_fn, make_train_step,
                             render_config)


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=pathlib.Path, help="a cusgs-train run folder (with .hydra/ and checkpoints/)")
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.0, 0.01, 0.05, 0.1, 0.3])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    config_path = args.run / ".hydra" / "config.yaml"
    if not config_path.is_file() or not (args.run / "checkpoints").is_dir():
        sys.exit(f"{args.run}: expected a cusgs-train run folder with .hydra/config.yaml and checkpoints/")

    cfg = OmegaConf.to_container(OmegaConf.load(config_path), resolve=True)
    tcfg = train_config(cfg)
    tcfg = dataclasses.replace(tcfg, prune=dataclasses.replace(tcfg.prune, strategy="feature_aware"))
    scene = load_data(cfg)
    width, height = scene.width, scene.height
    train_idx = scene.train_indices
    test_idx = scene.test_indices if len(scene.test_indices) else train_idx[:1]
    banks = targets = None
    if tcfg.features.enabled:
        feature_sets, banks = load_feature_targets(tcfg.features, scene, tcfg.seed, auto_extract=False)
        banks = {name: jnp.asarray(b) for name, b in banks.items()}
        targets = {name: jnp.asarray(fs.maps[train_idx].astype(np.float16)) for name, fs in feature_sets.items()}

    ckpt = Checkpointer(args.run / "checkpoints")
    meta = ckpt.metadata()
    state, _ = ckpt.restore(_template_state(tcfg, scene, int(meta["capacity"]), banks))
    ckpt.close()
    tx = make_optimizer(tcfg.optim, state.params, tcfg.iterations, scene.extent)

    # 1. statistics over every training view from the trained parameters (params untouched)
    step = make_train_step(tcfg, tx, width, height)
    images = jnp.asarray(scene.images[train_idx].astype(np.float32) / 255.0)
    start = time.perf_counter()
    stats_state = dataclasses.replace(state, step=jnp.int32(tcfg.prune.start))  # inside the statistics window
    for position in range(len(train_idx)):
        view = view_order(tcfg.seed, len(train_idx), position)
        batch = {"image": images[view], "viewmat": jnp.asarray(scene.viewmats[train_idx[view]]),
                 "K": jnp.asarray(scene.Ks[train_idx[view]]), "index": jnp.int32(view)}
        if targets is not None:
            batch["features"] = {name: t[view] for name, t in targets.items()}
            batch["banks"] = banks
        stepped, _ = step(_copy(stats_state), batch)
        stats_state = dataclasses.replace(stats_state, prune=stepped.prune)
    stats_seconds = time.perf_counter() - start
    alive = np.asarray(state.anchors.alive)

    render = make_render_fn(render_config(tcfg), width, height)
    rng = np.random.default_rng(args.seed)
    rows, models = [], []
    for ratio in args.ratios:
        prune = make_prune_step(dataclasses.replace(tcfg, prune=dataclasses.replace(tcfg.prune, ratio=ratio)))
        pruned, info = prune(_copy(stats_state))
        removed = int(info["pruned"])
        variants = {"feature_aware": pruned.anchors}
        if removed:
            drop = rng.choice(np.flatnonzero(alive), removed, replace=False)
            random_alive = alive.copy()
            random_alive[drop] = False
            variants["random"] = Anchors(state.anchors.centers, jnp.asarray(random_alive))
        for selection, anchors in variants.items():
            params, compact = compact_for_render(state.params, anchors)
            quality = evaluate_views(render, params, compact, scene, test_idx)  # also compiles this shape
            rows.append({"ratio": ratio, "selection": selection, "pruned": removed,
                         "alive_anchors": int(np.sum(np.asarray(anchors.alive))), "capacity": compact.capacity,
                         "params": count_parameters(state.params, np.asarray(anchors.alive), banks)["total"],
                         "psnr": quality["psnr"], "ssim": quality["ssim"]})
            models.append((params, compact))
    # timing round-robin over all models, best of --repeats medians, so load changes hit all alike
    for _ in range(args.repeats):
        for row, (params, compact) in zip(rows, models):
            ms = evaluate_views(render, params, compact, scene, test_idx, time_renders=True)["render_ms_per_view"]
            row["render_ms_per_view"] = min(ms, row.get("render_ms_per_view", np.inf))
    base = rows[0]["render_ms_per_view"]
    for row in rows:
        row["render_speedup"] = base / row["render_ms_per_view"]
        row["psnr_change_db"] = row["psnr"] - rows[0]["psnr"]
    print(json.dumps({
        "run": str(args.run), "width": width, "height": height, "held_out_views": len(test_idx),
        "training_views_for_statistics": len(train_idx), "statistics_seconds": stats_seconds,
        "repeats": args.repeats, "rows": rows,
        "env": {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": __import__("os").cpu_count(),
                "machine": platform.machine()},
    }, indent=1))


if __name__ == "__main__":
    main()
