"""Does today's train step compute what the step of an earlier revision did? Prints JSON.

    python experiments/step_equivalence.py [--old REV] [--steps 5]

Runs ``--steps`` single-view steps (growing and pruning statistics on) from the same initial state
on the same views with the step of REV (default e908d45, before active-Gaussian compaction and the
row-sparse update; a ``git worktree``, its own interpreter) and with today's step, once with
``optim.sparse=false`` (dense Adam, the update REV ran) and once with the default row-sparse
update. For each it reports the largest difference of every state leaf (parameters, Adam moments,
densification statistics) relative to that leaf's largest magnitude, and of the losses.

Today's dense step is not bit-identical to REV's: the compacted splatter sums gradients over the
active Gaussians only, in another order, so float32 reductions round differently; it must agree to
float32 tolerance. The sparse step differs by design from the second step on (unseen anchors keep
their Adam moments and do not move on momentum).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

REPO = pathlib.Path(__file__).resolve().parent.parent


def child(steps: int, sparse: str, out: str) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cusgs_jax.config import Config
    from cusgs_jax.densify.factory import make_strategies
    from cusgs_jax.testing.scenes import sfm_points
    from cusgs_jax.training.state import init_train_state
    from cusgs_jax.training.step import make_train_step
    from cusgs_jax.types import Camera

    width, height = 32, 24
    K = jnp.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    cfg = Config().replace(train=dict(iterations=50),
                           model=dict(voxel_size=0.25, n_offsets=4, latent_dim=8, hidden=16, appearance_dim=8,
                                      visible_fraction=1.0),
                           splat=dict(max_pairs_per_gaussian=40.0),
                           grow=dict(stats_start=0, start=5, stop=50, interval=5),
                           **({"optim": dict(sparse=sparse == "true")} if sparse != "absent" else {}))

    def batch(seed):
        rng = np.random.default_rng(seed)
        view = np.eye(4, dtype=np.float32)
        view[:3, 3] = rng.normal(0, 0.05, 3)
        return dict(image=jnp.asarray(rng.uniform(0, 1, (height, width, 3)).astype(np.float32)),
                    camera=Camera(K, jnp.asarray(view), width, height), index=jnp.int32(seed % 2))

    strategies = make_strategies(cfg)
    state, tx = init_train_state(cfg, sfm_points(), 2, 2.0, strategies)
    step = make_train_step(cfg, tx, strategies)
    losses = []
    for i in range(steps):
        state, metrics = step(state, batch(i))
        assert not any(int(metrics.get(k, 0)) for k in ("dropped_anchors", "dropped_gaussians", "dropped_pairs"))
        losses.append(float(metrics["loss"]))
    leaves = jax.tree_util.tree_leaves_with_path((state.trainable, state.opt_state, state.densify))
    arrays = {jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in leaves
              if np.issubdtype(np.asarray(leaf).dtype, np.floating)}
    np.savez(out, __losses__=np.asarray(losses), **arrays)


def run(src: pathlib.Path, steps: int, sparse: str, out: str) -> None:
    env = dict(os.environ, PYTHONPATH=str(src))
    subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps), "--sparse", sparse,
                    "--out", out], env=env, check=True, cwd=tempfile.gettempdir())


def compare(a_path: str, b_path: str) -> dict:
    import numpy as np

    a, b = np.load(a_path), np.load(b_path)
    shared = sorted(set(a.files) & set(b.files) - {"__losses__"})
    worst, name = 0.0, None
    for key in shared:
        scale = max(float(np.max(np.abs(a[key]))), 1e-30) if a[key].size else 1.0
        diff = float(np.max(np.abs(a[key] - b[key]))) / scale if a[key].size else 0.0
        if diff > worst:
            worst, name = diff, key
    la, lb = a["__losses__"], b["__losses__"]
    return dict(leaves_compared=len(shared), leaves_only_in_one=len(set(a.files) ^ set(b.files)),
                max_relative_leaf_difference=worst, worst_leaf=name,
                max_relative_loss_difference=float(np.max(np.abs(la - lb) / np.abs(la))),
                bit_identical=all(np.array_equal(a[k], b[k]) for k in shared) and np.array_equal(la, lb))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--old", default="e908d45")
    parser.add_argument("--old-src", type=pathlib.Path)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--sparse", default="absent", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.steps, args.sparse, args.out)
        return
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="step-equivalence-"))
    old_src, made = args.old_src, None
    if old_src is None:
        made = tmp / "old"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(made), args.old], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        old_src = made / "src"
    try:
        run(old_src, args.steps, "absent", str(tmp / "old.npz"))
        run(REPO / "src", args.steps, "false", str(tmp / "dense.npz"))
        run(REPO / "src", args.steps, "true", str(tmp / "sparse.npz"))
    finally:
        if made is not None:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(made)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    print(json.dumps(dict(old=args.old if args.old_src is None else str(old_src), steps=args.steps,
                          dense_vs_old=compare(str(tmp / "old.npz"), str(tmp / "dense.npz")),
                          sparse_vs_old=compare(str(tmp / "old.npz"), str(tmp / "sparse.npz"))), indent=1))


if __name__ == "__main__":
    main()
