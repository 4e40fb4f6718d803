"""Plots of a sweep's run records (matplotlib, headless), for ``cusgs-report``.

A *record* is one job of the sweep, as :func:`cusgs_jax.app.report.load_job` returns it; the
plots read its ``job``, ``status`` (``"ok"``, ``"incomplete"`` or ``"failed: ..."``), ``curve``
(held-out points ``{"step", "wall_s", "psnr", optional "feature_cosine", "feature_l2"}``),
``anchor_curve`` (``[(step, alive_anchors), ...]``), ``params``, ``psnr``, ``train_s``, ``run_s``,
``feature_cosine`` and ``feature_l2`` (float or None). :func:`write_plots` writes:

* ``psnr_vs_time.png`` -- held-out PSNR against training-clock seconds, one line per run;
* ``feature_error_vs_time.png`` -- feature cosine distance and L2 error against training-clock
  seconds (not written, and a stale copy removed, when no run evaluated feature fields);
* ``psnr_vs_size.png`` -- final PSNR against total parameters, :func:`pareto_front` highlighted;
* ``psnr_vs_job_time.png`` -- final PSNR against the whole job's seconds (``run_s``: ``eval.json``
  ``time.total``, compiles included, so the jobs that ran first carry the compiles later ones loaded
  from the persistent cache);
* ``anchors_vs_step.png`` -- alive anchors against training step, one line per run.

The time axes of the first two count the training clock, :data:`~cusgs_jax.eval.plots.CLOCK`: the loop's
steps and densification, not the first step's compile.

Failed jobs are left out; incomplete jobs are drawn with dashed lines from their partial logs.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from cusgs_jax.eval.plots import CLOCK_LABEL  # noqa: E402

__all__ = ["finite_or_none", "pareto_front", "write_plots"]

FIGSIZE, DPI = (8.0, 5.0), 120


def finite_or_none(value) -> float | None:
    """A finite float, or None for missing / non-numeric / NaN values."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def pareto_front(points) -> list[int]:
    """Indices of the points ``(size, psnr)`` that no other point dominates, sorted by size.

    ``j`` dominates ``i`` when ``size_j <= size_i`` and ``psnr_j >= psnr_i`` with at least one
    strict; identical points therefore are all on the front.
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best_smaller, k = [], -math.inf, 0
    while k < len(order):  # walk groups of equal size
        size = points[order[k]][0]
        group = []
        while k < len(order) and points[order[k]][0] == size:
            group.append(order[k])
            k += 1
        top = points[group[0]][1]  # the group is sorted by decreasing PSNR
        if top > best_smaller:
            front += [i for i in group if points[i][1] == top]
            best_smaller = top
    return front


def _finish(fig, axes, path: Path, n_labels: int) -> None:
    """Grid, legend (outside and small when there are many runs), save, close."""
    for ax in axes:
        ax.grid(alpha=0.3)
    if n_labels:
        if n_labels > 8:
            axes[0].legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
        else:
            axes[0].legend(fontsize=8)
    else:
        axes[0].text(0.5, 0.5, "no data", transform=axes[0].transAxes, ha="center", color="gray")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def _style(record) -> dict:
    return {"ls": "--" if record["status"] == "incomplete" else "-"}


def _plot_psnr_vs_time(runs, path):
    fig, ax = plt.subplots(figsize=FIGSIZE)
    n = 0
    for r, name, color in runs:
        pts = [(p["wall_s"], p["psnr"]) for p in r["curve"]
               if finite_or_none(p.get("wall_s")) is not None and finite_or_none(p.get("psnr")) is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", ms=3, color=color, label=name, **_style(r))
            n += 1
    ax.set(xlabel=CLOCK_LABEL, ylabel="held-out PSNR (dB)", title="PSNR against training time")
    _finish(fig, [ax], path, n)


def _feature_series(record, key):
    """[(wall_s, value)] from curve points with ``feature_<key>``, else the final eval point."""
    pts = [(p["wall_s"], p[f"feature_{key}"]) for p in record["curve"]
           if finite_or_none(p.get("wall_s")) is not None and finite_or_none(p.get(f"feature_{key}")) is not None]
    if not pts and record[f"feature_{key}"] is not None and record["train_s"] is not None:
        pts = [(record["train_s"], record[f"feature_{key}"])]
    return pts


def _plot_features(runs, path) -> bool:
    """Two panels (cosine distance, L2); returns False (and writes nothing) without features."""
    series = [(r, name, color, _feature_series(r, "cosine"), _feature_series(r, "l2")) for r, name, color in runs]
    series = [s for s in series if s[3] or s[4]]
    if not series:
        return False
    fig, axes = plt.subplots(2, 1, figsize=(FIGSIZE[0], 7.0), sharex=True)
    for r, name, color, cos, l2 in series:
        for ax, pts, label in ((axes[0], cos, name), (axes[1], l2, None)):
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=3 if len(pts) > 1 else 6, color=color, label=label, **_style(r))
    axes[0].set(ylabel="feature cosine distance (1 - cos)", title="feature error against training time")
    axes[1].set(ylabel="feature L2 error", xlabel=CLOCK_LABEL)
    _finish(fig, axes, path, len(series))
    return True


def _plot_psnr_vs_size(runs, path):
    fig, ax = plt.subplots(figsize=FIGSIZE)
    runs = [(r, name, color) for r, name, color in runs
            if r["status"] == "ok" and r["params"] is not None and r["psnr"] is not None]
    points = [(r["params"], r["psnr"]) for r, *_ in runs]
    for (r, name, color), (x, y) in zip(runs, points):
        ax.scatter([x], [y], color=color, s=30, zorder=3, label=name)
        ax.annotate(r["job"], (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    front = pareto_front(points)
    if front:
        xs, ys = zip(*(points[i] for i in front))
        ax.plot(xs, ys, color="black", lw=1.2, zorder=2, label="Pareto front")
        ax.scatter(xs, ys, s=110, facecolors="none", edgecolors="black", zorder=4)
    sizes = [x for x, _ in points if x > 0]
    if sizes and max(sizes) > 10 * min(sizes):
        ax.set_xscale("log")
    ax.set(xlabel="total parameters", ylabel="held-out PSNR (dB)", title="PSNR against model size")
    _finish(fig, [ax], path, len(runs) + bool(front))


def _plot_psnr_vs_job_time(runs, path):
    """Final PSNR against the whole job's seconds (``run_s``), one point per finished run."""
    fig, ax = plt.subplots(figsize=FIGSIZE)
    runs = [(r, name, color) for r, name, color in runs
            if r["status"] == "ok" and r.get("run_s") is not None and r["psnr"] is not None]
    for r, name, color in runs:
        ax.scatter([r["run_s"]], [r["psnr"]], color=color, s=30, zorder=3, label=name)
        ax.annotate(r["job"], (r["run_s"], r["psnr"]), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set(xlabel="whole job time (s): eval.json time.total, compiles included", ylabel="held-out PSNR (dB)",
           title="final PSNR against job time (the first jobs also compile what later ones load from the cache)")
    _finish(fig, [ax], path, len(runs))


def _plot_anchors(runs, path):
    fig, ax = plt.subplots(figsize=FIGSIZE)
    n = 0
    for r, name, color in runs:
        if r["anchor_curve"]:
            single = len(r["anchor_curve"]) == 1  # a run that just started: show its one point
            ax.plot(*zip(*r["anchor_curve"]), marker="o" if single else None, ms=5, color=color, label=name,
                    **_style(r))
            n += 1
    ax.set(xlabel="training step", ylabel="alive anchors", title="alive anchors during training")
    _finish(fig, [ax], path, n)


def write_plots(records, labels, out_dir) -> dict[str, Path]:
    """Write the plots of ``records`` (failed jobs skipped) into the existing folder ``out_dir``.

    ``labels[i]`` names ``records[i]`` in the legends (`` (incomplete)`` is appended for
    incomplete jobs); colours follow the record index. Returns ``{file name: path}`` of what was
    written; ``feature_error_vs_time.png`` is missing from it (and a stale copy removed) when no
    run has feature metrics.
    """
    out = Path(out_dir)
    cmap = plt.get_cmap("tab10" if len(records) <= 10 else "tab20")
    runs = [(r, label + (" (incomplete)" if r["status"] == "incomplete" else ""), cmap(i % cmap.N))
            for i, (r, label) in enumerate(zip(records, labels)) if not r["status"].startswith("failed")]
    written = {}
    for name, plot in (("psnr_vs_time.png", _plot_psnr_vs_time), ("psnr_vs_size.png", _plot_psnr_vs_size),
                       ("psnr_vs_job_time.png", _plot_psnr_vs_job_time), ("anchors_vs_step.png", _plot_anchors)):
        plot(runs, out / name)
        written[name] = out / name
    feature_path = out / "feature_error_vs_time.png"
    if _plot_features(runs, feature_path):
        written[feature_path.name] = feature_path
    else:
        feature_path.unlink(missing_ok=True)
    return written
