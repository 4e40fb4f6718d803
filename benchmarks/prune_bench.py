"""Render speed and quality of a trained model before and after feature-aware pruning; prints JSON.

Takes a finished run folder (``cusgs-train`` writes ``.hydra/config.yaml`` and
``checkpoints/``), restores the final state and, side by side in one process:

1. accumulates the pruning statistics over every training view once, from the
   trained parameters (the train step is run on a copy and only its
   ``PruneStats`` are kept, so the parameters never change);
2. for each ``--ratios`` value removes ``floor(ratio · alive)`` anchors with
   one :func:`cusgs_jax.densify.feature_prune.prune_pass` (no fine-tuning afterwards), and the
   same number of *randomly chosen* alive anchors as a baseline for the score;
3. renders every held-out view of the compacted model (dead slots dropped,
   ``cusgs_jax.model.anchors.compact``) and reports PSNR, SSIM and the median ms per
   view, best of ``--repeats`` passes taken round-robin over all models.

Ratio 0 is the unpruned model ("before"). Ratios of render time are the
meaningful numbers; absolute times on a shared machine are noisy.

    python benchmarks/prune_bench.py multirun/voxel_size/<date>/1 [--ratios 0 0.01 0.05 0.1 0.3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.training.inputs import view_order
from cusgs_jax.app.run import setup, start
from cusgs_jax.compose import compose_config
from cusgs_jax.densify.feature_prune import FeaturePruneStrategy, prune_pass
from cusgs_jax.eval.views import count_parameters, evaluate_views
from cusgs_jax.model.anchors import compact
from cusgs_jax.run_folder import CHECKPOINTS_DIR, HYDRA_DIR
from cusgs_jax.training.step import make_train_step
from cusgs_jax.types import Camera


def _copy(tree):
    return jax.tree_util.tree_map(lambda x: jnp.array(x, copy=True), tree)


def _restore(run: pathlib.Path, scratch: str):
    """The run's final state, ``(session, loop)`` restored through :func:`cusgs_jax.app.run.setup` and
    :func:`~cusgs_jax.app.run.start` (its logs untouched)."""
    overrides = [line.strip()[2:] for line in (run / HYDRA_DIR / "overrides.yaml").read_text().splitlines()
                 if line.strip().startswith("- ")]
    cfg = compose_config(overrides)
    cfg = cfg.replace(train=dict(resume=True, checkpoint_dir=str(run / CHECKPOINTS_DIR), progress=False),
                      prune=dict(strategy="feature_aware"))
    session = setup(cfg, scratch)
    return session, start(session)


def _prune_statistics(session, loop) -> tuple[object, float]:
    """PruneStats over every training view once, from the trained parameters (which stay untouched)."""
    cfg, scene, idx = session.cfg, session.scene, session.train_idx
    step = make_train_step(cfg, loop.tx, session.strategies, loop.capacities)
    images = jnp.asarray(scene.images[idx].astype(np.float32) / 255.0)
    start = time.perf_counter()
    stats_state = loop.state.replace(step=jnp.int32(cfg.prune.start))  # inside the statistics window
    for position in range(len(idx)):
        view = view_order(cfg.train.seed, len(idx), position)
        batch = {"image": images[view], "camera": Camera.of_scene(scene, int(idx[view])),
                 "index": jnp.int32(view)}
        if session.banks is not None:
            batch["features"] = {name: t[view] for name, t in session.targets.items()}
            batch["banks"] = session.banks
        stepped, _ = step(_copy(stats_state), batch)
        stats_state = stats_state.replace(densify={**stats_state.densify, FeaturePruneStrategy.name:
                                                   stepped.densify[FeaturePruneStrategy.name]})
    return stats_state.densify[FeaturePruneStrategy.name], time.perf_counter() - start


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=pathlib.Path, help="a cusgs-train run folder (with .hydra/ and checkpoints/)")
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.0, 0.01, 0.05, 0.1, 0.3])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not (args.run / HYDRA_DIR / "overrides.yaml").is_file() or not (args.run / CHECKPOINTS_DIR).is_dir():
        sys.exit(f"{args.run}: expected a cusgs-train run folder with .hydra/overrides.yaml and checkpoints/")
    with tempfile.TemporaryDirectory() as scratch:
        session, loop = _restore(args.run, scratch)
        stats, stats_seconds = _prune_statistics(session, loop)
        session.ckpt.close()
    state, scene, prune_cfg = loop.state, session.scene, session.cfg.prune
    test_idx = session.test_idx
    alive = np.asarray(state.anchors.alive)
    rng = np.random.default_rng(args.seed)
    rows, models = [], []
    for ratio in args.ratios:
        pruned, _, info = prune_pass(state.anchors, stats, dataclasses.replace(prune_cfg, ratio=ratio))
        removed = int(info["pruned"])
        variants = {"feature_aware": pruned}
        if removed:
            drop = rng.choice(np.flatnonzero(alive), removed, replace=False)
            random_alive = alive.copy()
            random_alive[drop] = False
            variants["random"] = state.anchors.replace(alive=jnp.asarray(random_alive))
        for selection, anchors in variants.items():
            compacted = compact(anchors)
            quality = evaluate_views(loop.render, compacted, state.nets, scene, test_idx)  # also compiles
            rows.append({"ratio": ratio, "selection": selection, "pruned": removed,
                         "alive_anchors": int(np.sum(np.asarray(anchors.alive))), "capacity": compacted.capacity,
                         "params": count_parameters(anchors, state.nets, session.banks)["total"],
                         "psnr": quality["psnr"], "ssim": quality["ssim"]})
            models.append(compacted)
    # timing round-robin over all models, best of --repeats medians, so load changes hit all alike
    for _ in range(args.repeats):
        for row, anchors in zip(rows, models):
            ms = evaluate_views(loop.render, anchors, state.nets, scene, test_idx,
                                time_renders=True)["render_ms_per_view"]
            row["render_ms_per_view"] = min(ms, row.get("render_ms_per_view", np.inf))
    base = rows[0]["render_ms_per_view"]
    for row in rows:
        row["render_speedup"] = base / row["render_ms_per_view"]
        row["psnr_change_db"] = row["psnr"] - rows[0]["psnr"]
    print(json.dumps({
        "run": str(args.run), "width": scene.width, "height": scene.height, "held_out_views": len(test_idx),
        "training_views_for_statistics": len(session.train_idx), "statistics_seconds": stats_seconds,
        "repeats": args.repeats, "rows": rows,
        "env": {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
                "machine": platform.machine()},
    }, indent=1))


if __name__ == "__main__":
    main()
