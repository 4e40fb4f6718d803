"""Train-step and held-out-render time of two revisions of this repository, side by side; prints JSON.

Each revision runs in its own interpreter with its own ``src/`` on ``PYTHONPATH`` (the old one
from a ``git worktree`` this script makes, or a folder given with ``--old-src``), on the same
scene, alternately: round r runs revision A then B (B then A on odd rounds), so load from
other work on the shared machine affects both alike. A round (``--child``):

1. loads the scene (``--scene``: ``demo`` = the built-in 160×120 demo scene, or a COLMAP/demo
   scene folder), builds the initial state (anchors from the SfM points, as ``cusgs-train``)
   and the step with that revision's own API, RGB only;
2. sizes the work capacities as ``cusgs-train`` does (today's revision: probed views' need with
   headroom; older revisions: the config's first guesses), runs ``--warmup`` steps (compilation and any capacity growth with replay happen here),
   then times ``--steps`` steps (median, each to ``block_until_ready``), replaying a step
   whose work did not fit — none did in the timed steps of any reported run
   (``replays_timed``);
3. times the held-out render (``make_render_fn`` on the compacted anchors, median over the
   held-out views after one compiling call) and reports the process's peak RSS.

The parent prints per-round step-time ratios old/new and their median. With ``--lockstep`` both
children run at once and take turns step by step (the parent signals one, waits for its step,
then the other; who goes first alternates), and each round also reports the median of the
per-step-pair ratios — on a machine whose speed drifts within seconds this is the steadier number.

    python benchmarks/compare_revisions.py --old e908d45 --scene demo --rounds 3
    python benchmarks/compare_revisions.py --old-src /tmp/old/src --scene demo --lockstep --steps 60 --rounds 1
    python benchmarks/compare_revisions.py --old e908d45 --scene ~/.cache/cusgs_jax/scale_bench/<scene> \\
        --steps 5 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parent.parent


# --- child: one revision, one round ------------------------------------------------------------


def child(args) -> dict:
    import inspect

    import jax
    import jax.numpy as jnp
    import numpy as np

    from cusgs_jax.config import Config
    try:
        from cusgs_jax.config import DataConfig
        from cusgs_jax.data.loader import load_scene as _load_scene

        def load_scene(path, holdout_every):
            return _load_scene(path, DataConfig(format="colmap", holdout_every=holdout_every))
    except ImportError:  # revisions before data/loader.py: the COLMAP keyword loader
        from cusgs_jax.data.colmap import load_scene
    from cusgs_jax.data.normalize import normalize_scene
    try:
        from cusgs_jax.densify.factory import make_strategies
    except ImportError:  # revisions before densify/factory.py kept it in densify/base.py
        from cusgs_jax.densify.base import make_strategies
    from cusgs_jax.model.anchors import compact
    from cusgs_jax.training import capacity
    from cusgs_jax.training.render import make_render_fn
    from cusgs_jax.app.resolve import resolve_voxel_size
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.training.step import make_train_step
    from cusgs_jax.types import Camera

    path = args.scene
    if path == "demo":
        from cusgs_jax.data.demo import demo_scene_path
        path = str(demo_scene_path())
    cfg = Config().replace(train=dict(iterations=30_000, seed=args.seed), features=dict(models=()))
    scene, _ = normalize_scene(load_scene(path, holdout_every=8))
    cfg = resolve_voxel_size(cfg, scene.points)
    strategies = make_strategies(cfg)
    train_idx = scene.train_indices
    state, tx = init_train_state(cfg, scene.points, len(train_idx), scene.extent, strategies)
    new_api = "capacities" in inspect.signature(make_train_step).parameters
    caps = cfg
    if new_api:  # the first capacities as the shell sizes them: probed views' need with headroom
        from cusgs_jax.training.render import most_work
        positions = np.unique(np.linspace(0, len(train_idx) - 1, min(8, len(train_idx))).round().astype(int))
        needs = most_work(state.anchors, state.nets, [(Camera.of_scene(scene, int(train_idx[p])), jnp.int32(p))
                                                      for p in positions], cfg)
        caps = capacity.Capacities.fitted(needs, state.anchors.capacity, cfg.model.n_offsets)
    images = jnp.asarray(scene.images.astype(np.float32) / 255.0)

    def build(caps):
        return make_train_step(cfg, tx, strategies, caps) if new_api else make_train_step(caps, tx, strategies)

    def grow(caps, metrics):
        if new_api:
            return caps.grown(metrics, state.anchors.capacity, cfg.model.n_offsets)
        model = caps.model
        from cusgs_jax.model.decode import num_visible_slots
        gaussians = num_visible_slots(state.anchors.capacity, model.visible_fraction) * model.n_offsets
        return capacity.grow_for(caps, metrics, state.anchors.capacity, gaussians)

    def dropped(metrics):
        return any(int(metrics.get(k, 0)) for k in ("dropped_anchors", "dropped_gaussians", "dropped_pairs"))

    step_fn, replays, compile_s, times, replays_timed = build(caps), 0, None, [], 0
    for i in range(args.warmup + args.steps):
        if args.lockstep and i >= args.warmup:
            from lockstep import wait_turn
            wait_turn(first=i == args.warmup)  # the other revision is idle while this one steps
        v = int(train_idx[i % len(train_idx)])
        batch = dict(image=images[v], camera=Camera.of_scene(scene, v), index=jnp.int32(i % len(train_idx)))
        while True:
            start = time.perf_counter()
            state, metrics = step_fn(state, batch)
            metrics = jax.device_get(metrics)
            elapsed = time.perf_counter() - start
            if compile_s is None:
                compile_s = elapsed
            if not dropped(metrics):
                break
            caps = grow(caps, metrics)
            step_fn, replays = build(caps), replays + 1
            replays_timed += i >= args.warmup
        if i >= args.warmup:
            times.append(elapsed)
            if args.lockstep:
                from lockstep import report_step
                report_step(elapsed)
    # held-out render of the compacted model
    anchors = compact(state.anchors)
    render = make_render_fn(cfg, caps) if new_api else make_render_fn(cfg)
    held_out = scene.test_indices[: args.render_views]
    render_times = []
    for j, v in enumerate([held_out[0]] + list(held_out)):
        start = time.perf_counter()
        (image,) = render(anchors, state.nets, Camera.of_scene(scene, int(v)), jnp.int32(0))
        jax.block_until_ready(image)
        if j:
            render_times.append(time.perf_counter() - start)
    return dict(capacities=caps.as_dict() if new_api else None, median_step_s=float(np.median(times)), step_times_s=times, compile_s=compile_s,
                replays=replays, replays_timed=replays_timed, alive_anchors=int(np.sum(state.anchors.alive)),
                capacity=state.anchors.capacity, width=scene.width, height=scene.height,
                views=len(scene.names), points=len(scene.points), last_loss=float(metrics["loss"]),
                visible_anchors=int(metrics["visible_anchors"]), pairs=int(metrics["pairs"]),
                active_gaussians=int(metrics["active_gaussians"]) if "active_gaussians" in metrics else None,
                render_ms_per_view=1000 * float(np.median(render_times)),
                peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


# --- parent ------------------------------------------------------------------------------------


def worktree(rev: str) -> pathlib.Path:
    """A detached ``git worktree`` of ``rev`` in a temporary folder (removed at exit)."""
    folder = pathlib.Path(tempfile.mkdtemp(prefix="cusgs-old-"))
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(folder), rev], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return folder


def run_child(src: pathlib.Path, args) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src))
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--scene", args.scene, "--steps", str(args.steps),
           "--warmup", str(args.warmup), "--render-views", str(args.render_views), "--seed", str(args.seed)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    if proc.returncode:
        raise SystemExit(f"child on {src} failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def lockstep(old_src: pathlib.Path, new_src: pathlib.Path, args) -> dict:
    """Both revisions' children at once, taking turns step by step (``lockstep.py``)."""
    from lockstep import run_pairs

    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--lockstep", "--scene", args.scene,
           "--steps", str(args.steps), "--warmup", str(args.warmup), "--render-views", str(args.render_views),
           "--seed", str(args.seed)]
    out = run_pairs({name: (cmd, dict(os.environ, PYTHONPATH=str(src)))
                     for name, src in (("old", old_src), ("new", new_src))}, args.steps)
    out["pair_ratios_old_over_new"] = out.pop("pair_ratios")
    out["median_pair_ratio_old_over_new"] = out.pop("median_pair_ratio")
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--old", default="e908d45", help="git revision to compare against (default: the "
                        "revision before active-Gaussian compaction)")
    parser.add_argument("--old-src", type=pathlib.Path, help="use this src/ folder instead of a worktree of --old")
    parser.add_argument("--new-src", type=pathlib.Path, default=REPO / "src")
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--render-views", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lockstep", action="store_true",
                        help="run both revisions at once, taking turns step by step (ratios per step pair)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)), flush=True)
        return
    made = None
    old_src = args.old_src
    if old_src is None:
        made = worktree(args.old)
        old_src = made / "src"
    try:
        rounds = []
        for r in range(args.rounds):
            order = [("old", old_src), ("new", args.new_src)]
            if r % 2:
                order.reverse()
            if args.lockstep:
                result = lockstep(old_src, args.new_src, args)
            else:
                result = {name: run_child(src, args) for name, src in order}
            result["ratio_old_over_new"] = result["old"]["median_step_s"] / result["new"]["median_step_s"]
            result["render_ratio_old_over_new"] = (result["old"]["render_ms_per_view"]
                                                   / result["new"]["render_ms_per_view"])
            rounds.append(result)
            print(json.dumps(dict(round=r, old_step_s=result["old"]["median_step_s"],
                                  median_pair_ratio=result.get("median_pair_ratio_old_over_new"),
                                  new_step_s=result["new"]["median_step_s"],
                                  ratio=result["ratio_old_over_new"])), file=sys.stderr, flush=True)
    finally:
        if made is not None:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(made)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import statistics
    print(json.dumps(dict(
        benchmark="compare_revisions", old=args.old if args.old_src is None else str(args.old_src),
        scene=args.scene, steps=args.steps, warmup=args.warmup,
        median_ratio_old_over_new=statistics.median(r["ratio_old_over_new"] for r in rounds),
        median_render_ratio_old_over_new=statistics.median(r["render_ratio_old_over_new"] for r in rounds),
        rounds=rounds), indent=1))


if __name__ == "__main__":
    main()
