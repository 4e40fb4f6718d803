"""The Pareto search's runs next to hand-picked voxel-size / pruning-ratio runs at the same schedule.

    python experiments/pareto_vs_handpicked.py <pareto sweep> <hand-picked sweep> [...] > comparison.md

Prints one Markdown table of every finished run (source, settings, PSNR, parameters), with the
front of all of them together marked, and which hand-picked runs a searched run dominates.
"""

from __future__ import annotations

import sys
from pathlib import Path

from cusgs_jax.app.report import collect, run_label, swept_keys
from cusgs_jax.eval.sweep_plots import pareto_front


def main(roots) -> None:
    runs = []
    for i, root in enumerate(roots):
        records = [r for r in collect(root) if r["status"] == "ok"]
        keys, _ = swept_keys(records)
        source = "search" if i == 0 else Path(root).name
        runs += [dict(r, source=source, label=run_label(r, keys)) for r in records]
    front = set(pareto_front([(r["params"], r["psnr"]) for r in runs]))
    print("| source | job | settings | PSNR (dB) | params | on the joint front |")
    print("|---|---|---|---:|---:|---|")
    for i, r in sorted(enumerate(runs), key=lambda ir: ir[1]["params"]):
        print(f"| {r['source']} | {r['job']} | {r['label']} | {r['psnr']:.2f} | {r['params']:,.0f} | "
              f"{'★' if i in front else ''} |")
    print()
    for h in (r for r in runs if r["source"] != "search"):
        better = [s for s in runs if s["source"] == "search" and s["params"] <= h["params"] and s["psnr"] >= h["psnr"]]
        verdict = ", ".join(f"job {s['job']} ({s['psnr']:.2f} dB, {s['params']:,.0f})" for s in better) or "none"
        print(f"* hand-picked {h['source']} {h['label']} ({h['psnr']:.2f} dB, {h['params']:,.0f}): "
              f"dominated by searched {verdict}")


if __name__ == "__main__":
    main(sys.argv[1:])
