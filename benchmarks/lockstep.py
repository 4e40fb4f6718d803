"""Two benchmark children that take turns step by step, so a load change lands on both alike.

A child prints ``READY`` when it is warm, then for each timed step reads one line from stdin (its
turn), runs the step and prints ``STEP <seconds>``; its last stdout line is its JSON result. The
parent (:func:`run_pairs`) starts both, waits until both are warm, hands out the turns (who goes
first alternates) and returns both results with the per-pair ratios.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile


def wait_turn(first: bool) -> None:
    """In a child, before a timed step: say ``READY`` once, then block until the parent's turn signal."""
    if first:
        print("READY", flush=True)
    sys.stdin.readline()


def report_step(seconds: float) -> None:
    """In a child, after a timed step."""
    print(f"STEP {seconds!r}", flush=True)


def run_pairs(commands: dict, steps: int) -> dict:
    """``commands``: {name: (argv, env)} for exactly two children. Returns ``{name: result, ...,
    "pair_ratios": [first/second per step], "median_pair_ratio": ...}`` (names in ``commands``' order)."""
    procs = {name: subprocess.Popen(argv, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                    cwd=tempfile.gettempdir())
             for name, (argv, env) in commands.items()}
    names = list(procs)

    def read(name):
        line = procs[name].stdout.readline()
        if not line:
            raise SystemExit(f"the {name} child ended early (exit {procs[name].wait()})")
        return line.strip()

    for name in names:  # compile and warm up one after the other
        while read(name) != "READY":
            pass
    times = {name: [] for name in names}
    for i in range(steps):
        for name in (names if i % 2 == 0 else names[::-1]):
            procs[name].stdin.write("go\n")
            procs[name].stdin.flush()
            line = read(name)
            while not line.startswith("STEP "):
                line = read(name)
            times[name].append(float(line.split()[1]))
    results = {}
    for name, proc in procs.items():
        out, _ = proc.communicate()
        if proc.returncode:
            raise SystemExit(f"the {name} child failed (exit {proc.returncode})")
        results[name] = json.loads(out.strip().splitlines()[-1])
    ratios = [a / b for a, b in zip(times[names[0]], times[names[1]])]
    return dict(results, pair_ratios=ratios, median_pair_ratio=statistics.median(ratios))
