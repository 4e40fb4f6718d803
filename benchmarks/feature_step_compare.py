"""The default demo run's training step (RGB + the demo's feature models) of two source trees, side by side.

Each round runs the old then the new tree (``--old-src`` / ``--new-src``, e.g. a ``git worktree`` of the
earlier revision's ``src``) in its own interpreter: setup as ``cusgs-train`` does with no overrides,
5 warm-up steps, then the median of 40 timed steps (replays included, as the run loop does). Prints one
JSON line per tree and round, then the per-round ratios old/new.

    git worktree add --detach /tmp/old 834d7df
    python benchmarks/feature_step_compare.py --old-src /tmp/old/src --new-src src --rounds 3
    python benchmarks/feature_step_compare.py --old-src /tmp/old/src --new-src src --rounds 1 --lockstep
    python benchmarks/feature_step_compare.py --old-src /tmp/old/src --new-src src --lockstep \
        --set 'features.models=[{name: vgg16}]'
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


def child(src: str, lockstep: bool = False, overrides=()) -> dict:
    from cusgs_jax.app import loop as run_loop
    from cusgs_jax.app.session import setup
    from cusgs_jax.compose import compose_config

    session = setup(compose_config(["train.progress=false", *overrides]), tempfile.mkdtemp())
    loop = run_loop.start(session)
    batch = session.batches
    for step in range(5):
        (getattr(run_loop, "exact_step", None) or run_loop._exact_step)(session, loop, batch(step))
    times = []
    for step in range(5, 45):
        if lockstep:
            from lockstep import wait_turn
            wait_turn(first=step == 5)
        start = time.perf_counter()
        (getattr(run_loop, "exact_step", None) or run_loop._exact_step)(session, loop, batch(step))
        times.append(time.perf_counter() - start)
        if lockstep:
            from lockstep import report_step
            report_step(times[-1])
    return dict(src=src, median_step_s=statistics.median(times))


def _set_args(args) -> list[str]:
    return [item for value in args.set for item in ("--set", value)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old-src", required=True)
    ap.add_argument("--new-src", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--lockstep", action="store_true",
                    help="run both trees at once, taking turns step by step (per-pair ratios; lockstep.py)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for both trees (repeatable), e.g. features.models=[{name: vgg16}]")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.lockstep, args.set)))
        return
    if args.lockstep:
        from lockstep import run_pairs
        for r in range(args.rounds):
            cmds = {name: ([sys.executable, os.path.abspath(__file__), "--old-src", args.old_src, "--new-src",
                            args.new_src, "--lockstep", "--child", src, *_set_args(args)],
                           dict(os.environ, PYTHONPATH=os.path.abspath(src)))
                    for name, src in (("old", args.old_src), ("new", args.new_src))}
            out = run_pairs(cmds, 40)
            print(json.dumps(dict(round=r, old=out["old"], new=out["new"], median_pair_ratio_old_over_new=out[
                "median_pair_ratio"], pair_ratios_old_over_new=out["pair_ratios"])), flush=True)
        return
    rows = []
    for _ in range(args.rounds):
        for src in (args.old_src, args.new_src):
            env = dict(os.environ, PYTHONPATH=os.path.abspath(src))
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--old-src", args.old_src,
                                  "--new-src", args.new_src, "--child", src, *_set_args(args)], env=env,
                                 capture_output=True,
                                 text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
    ratios = [a["median_step_s"] / b["median_step_s"] for a, b in zip(rows[::2], rows[1::2])]
    print(json.dumps(dict(ratios_old_over_new=ratios, median_ratio=statistics.median(ratios))))


if __name__ == "__main__":
    main()
