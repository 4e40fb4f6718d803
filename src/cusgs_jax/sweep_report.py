"""``cusgs-report``: one table and a few plots for a Hydra sweep made by ``cusgs-train -m ...``.

Usage: ``cusgs-report <multirun folder> [--out DIR]``.

Input. A *job folder* is any folder under the multirun folder that holds ``.hydra/config.yaml``,
``eval.json`` or ``failed.json`` (Hydra numbers them ``0/``, ``1/``, ...). What is read from it:

* ``.hydra/overrides.yaml`` -- the job's command-line overrides (``["prune.ratio=0.01", ...]``).
* ``eval.json`` -- written when a run finishes: ``psnr``, ``ssim``, ``params.total``,
  ``alive_anchors``, ``train_wall_s``, ``render_ms_per_view``, optional ``render_ms_before_prune``,
  optional ``features.models.<name>.{cosine,l2}`` and the held-out ``curve``.
* ``eval_curve.jsonl`` -- the held-out curve so far (used while a run is still going).
* ``metrics.jsonl`` -- training log rows; ``step`` and ``alive_anchors`` are used.
* ``failed.json`` -- ``{"error": "Type: message", "traceback": ...}`` when the job raised.

A job is ``ok`` (has ``eval.json``), ``failed: <first error line>`` (has ``failed.json``, or an
``eval.json`` that cannot be read) or ``incomplete`` (neither: still running or killed).

Output, in ``<root>/report/`` unless ``--out`` says otherwise:

* ``report.md`` -- the table (CUS-GS Table 4 style, rounded) and a line naming the best-PSNR and
  the smallest run; also printed to stdout.
* ``report.csv`` -- the same rows at full precision with one column per swept override key.
* ``psnr_vs_time.png`` -- held-out PSNR against training wall-clock seconds, one line per run.
* ``feature_error_vs_time.png`` -- feature cosine distance and L2 error against wall-clock
  seconds; not written when no run evaluated feature fields.
* ``psnr_vs_size.png`` -- final PSNR against total parameters, Pareto front highlighted.
* ``anchors_vs_step.png`` -- alive anchors against training step, one line per run.

Failed jobs are listed in the table but left out of the plots; incomplete jobs are plotted with
dashed lines from their partial logs.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import sys
from pathlib import Path

import matplotlib
import yaml

matplotlib.use("Agg")
import matplotlib.pyplot as plt

#: Metric columns: (record / CSV key, Markdown header, Markdown format, meaning).
METRICS = [
    ("params", "params", "{:,.0f}", "total trained parameters (eval.json params.total)"),
    ("anchors", "anchors", "{:,.0f}", "alive anchors at the end of training"),
    ("ssim", "SSIM", "{:.4f}", "held-out SSIM"),
    ("psnr", "PSNR", "{:.2f}", "held-out PSNR in dB"),
    ("feature_cosine", "feat. cos", "{:.4f}",
     "cosine distance 1-cos of the rendered feature maps, mean over feature models (lower is better)"),
    ("feature_l2", "feat. L2", "{:.4f}", "L2 error of the rendered feature maps, mean over feature models"),
    ("train_s", "train (s)", "{:.1f}", "training wall-clock seconds"),
    ("render_ms", "render ms/view", "{:.1f}", "median held-out render time per view"),
    ("render_ms_before_prune", "render ms/view at 1st prune", "{:.1f}",
     "render time per view of the model just before the first pruning pass (pruning runs only; it has "
     "fewer anchors than the final model when growing continues afterwards)"),
]
MARKERS = (".hydra/config.yaml", "eval.json", "failed.json")
FIGSIZE, DPI = (8.0, 5.0), 120


# ----------------------------------------------------------------------------- reading


def _natural_key(text: str) -> list:
    """'10/x' sorts after '2/x': digit runs compare as numbers."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", text)]


def find_jobs(root) -> list[Path]:
    """Job folders under ``root`` (``root`` itself included), in natural path order.

    A job folder holds ``.hydra/config.yaml``, ``eval.json`` or ``failed.json``; the search does
    not descend into job folders or hidden folders.
    """
    root = Path(root)
    jobs = []
    for folder, subdirs, _ in os.walk(root):
        folder = Path(folder)
        if any((folder / marker).is_file() for marker in MARKERS):
            jobs.append(folder)
            subdirs.clear()
        else:
            subdirs[:] = [d for d in subdirs if not d.startswith(".")]
    return sorted(jobs, key=lambda p: _natural_key(p.relative_to(root).as_posix()))


def _num(value) -> float | None:
    """A finite float, or None for missing / non-numeric / NaN values."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def _read_jsonl(path: Path) -> list[dict]:
    """Rows of a JSON-lines file; unreadable lines (e.g. a half-written last line) are skipped.

    Rows repeated for the same ``step`` (a resumed run appends again) keep the last one.
    """
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict):
            rows.append(row)
    if rows and all(_num(r.get("step")) is not None for r in rows):
        rows = sorted({r["step"]: r for r in rows}.values(), key=lambda r: r["step"])
    return rows


def _read_overrides(job: Path) -> dict[str, str | None]:
    """``{"prune.ratio": "0.01", ...}`` from ``.hydra/overrides.yaml`` (leading ``+`` dropped)."""
    try:
        items = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return {}
    overrides = {}
    for item in items if isinstance(items, list) else []:
        key, eq, value = str(item).partition("=")
        overrides[key.lstrip("+")] = value if eq else None
    return overrides


def _first_line(text) -> str:
    lines = str(text).strip().splitlines()
    return lines[0].strip() if lines else "unknown error"


def _mean(values) -> float | None:
    values = [v for v in map(_num, values) if v is not None]
    return sum(values) / len(values) if values else None


def _eval_metrics(result: dict) -> dict:
    """The metric columns (see :data:`METRICS`) from a parsed ``eval.json``."""
    params = result.get("params")
    features = result.get("features")
    models = features.get("models") if isinstance(features, dict) else None
    models = [m for m in models.values() if isinstance(m, dict)] if isinstance(models, dict) else []
    return {
        "params": _num(params.get("total")) if isinstance(params, dict) else _num(params),
        "anchors": _num(result.get("alive_anchors")),
        "ssim": _num(result.get("ssim")),
        "psnr": _num(result.get("psnr")),
        "feature_cosine": _mean(m.get("cosine") for m in models),
        "feature_l2": _mean(m.get("l2") for m in models),
        "train_s": _num(result.get("train_wall_s")),
        "render_ms": _num(result.get("render_ms_per_view")),
        "render_ms_before_prune": _num(result.get("render_ms_before_prune")),
    }


def load_job(path, root=None) -> dict:
    """One record for one job folder.

    Keys: ``job`` (path relative to ``root``, or the folder name), ``path``, ``overrides``
    (key -> value string), ``status``, the :data:`METRICS` keys (float or None; None unless
    ``ok``), ``curve`` (held-out points ``{"step", "wall_s", "psnr", ...}``) and ``anchor_curve``
    (``[(step, alive_anchors), ...]`` from ``metrics.jsonl``).
    """
    path = Path(path)
    record = dict(job=path.relative_to(root).as_posix() if root is not None else path.name,
                  path=path, overrides=_read_overrides(path), status="incomplete",
                  **{key: None for key, *_ in METRICS})
    record["curve"] = _read_jsonl(path / "eval_curve.jsonl")
    record["anchor_curve"] = [(r["step"], r["alive_anchors"]) for r in _read_jsonl(path / "metrics.jsonl")
                              if _num(r.get("step")) is not None and _num(r.get("alive_anchors")) is not None]
    if (path / "failed.json").is_file():
        try:
            error = json.loads((path / "failed.json").read_text()).get("error") or "unknown error"
        except (OSError, ValueError, AttributeError) as exc:
            error = f"unreadable failed.json ({type(exc).__name__}: {_first_line(exc)})"
        record["status"] = "failed: " + _first_line(error)
    elif (path / "eval.json").is_file():
        try:
            result = json.loads((path / "eval.json").read_text())
            if not isinstance(result, dict):
                raise TypeError(f"expected a JSON object, got {type(result).__name__}")
        except (OSError, ValueError, TypeError) as exc:
            record["status"] = f"failed: unreadable eval.json ({type(exc).__name__}: {_first_line(exc)})"
        else:
            record.update(_eval_metrics(result), status="ok")
            curve = [p for p in result.get("curve") or [] if isinstance(p, dict)]
            record["curve"] = curve or record["curve"]
    return record


def collect(root) -> list[dict]:
    """:func:`load_job` for every job folder under ``root``."""
    return [load_job(job, root) for job in find_jobs(root)]


# ----------------------------------------------------------------------------- summarising


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


def swept_keys(records) -> tuple[list[str], list[str]]:
    """(override keys that differ between jobs, ``key=value`` overrides shared by every job)."""
    keys = list(dict.fromkeys(k for r in records for k in r["overrides"]))
    swept, fixed = [], []
    for key in keys:
        values = {r["overrides"].get(key, "\0missing") for r in records}
        if len(values) == 1:
            value = values.pop()
            fixed.append(key if value is None else f"{key}={value}")
        else:
            swept.append(key)
    return swept, fixed


def run_label(record, keys) -> str:
    """``"prune.ratio=0.01, prune.passes=10"`` from the swept ``keys``; ``"(defaults)"`` if none."""
    parts = [k if record["overrides"][k] is None else f"{k}={record['overrides'][k]}"
             for k in keys if k in record["overrides"]]
    return ", ".join(parts) or "(defaults)"


def _cell(value, fmt) -> str:
    return "" if value is None else fmt.format(value)


def render_markdown(records, keys, fixed) -> str:
    """The Markdown report: header, table (one row per job) and the best / smallest line."""
    counts = {s: sum(r["status"].split(":")[0] == s for r in records) for s in ("ok", "failed", "incomplete")}
    lines = ["# Sweep report", "",
             f"{len(records)} jobs: {counts['ok']} ok, {counts['failed']} failed, {counts['incomplete']} incomplete."]
    if fixed:
        lines.append("Shared overrides: " + ", ".join(f"`{o}`" for o in fixed) + ".")
    header = ["job", "run", "status"] + [h for _, h, *_ in METRICS]
    lines += ["", "| " + " | ".join(header) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * len(METRICS)) + "|"]
    for r in records:
        status = r["status"] if len(r["status"]) <= 120 else r["status"][:117] + "..."
        cells = [r["job"], run_label(r, keys), status] + [_cell(r[k], fmt) for k, _, fmt, _ in METRICS]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    ok = [r for r in records if r["status"] == "ok"]
    best = max((r for r in ok if r["psnr"] is not None), key=lambda r: r["psnr"], default=None)
    small = min((r for r in ok if r["params"] is not None), key=lambda r: r["params"], default=None)
    lines.append("")
    if best is None and small is None:
        lines.append("No job has finished yet.")
    else:
        summary = []
        if best is not None:
            summary.append(f"Best PSNR: job `{best['job']}` ({run_label(best, keys)}), {best['psnr']:.2f} dB")
        if small is not None:
            summary.append(f"smallest model: job `{small['job']}` ({run_label(small, keys)}), "
                           f"{small['params']:,.0f} parameters")
        lines.append("; ".join(summary) + ".")
    return "\n".join(lines) + "\n"


def _write_csv(records, keys, path: Path) -> None:
    """``job``, one column per swept key, ``status``, then the :data:`METRICS` (full precision)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["job", *keys, "status", *(k for k, *_ in METRICS)])
        for r in records:
            sweeps = [r["overrides"].get(k) or "" for k in keys]
            values = ["" if r[k] is None else (int(r[k]) if k in ("params", "anchors") else r[k])
                      for k, *_ in METRICS]
            writer.writerow([r["job"], *sweeps, r["status"], *values])


# ----------------------------------------------------------------------------- plotting


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
               if _num(p.get("wall_s")) is not None and _num(p.get("psnr")) is not None]
        if pts:
            ax.plot(*zip(*pts), marker="o", ms=3, color=color, label=name, **_style(r))
            n += 1
    ax.set(xlabel="training wall-clock time (s)", ylabel="held-out PSNR (dB)", title="PSNR against training time")
    _finish(fig, [ax], path, n)


def _feature_series(record, key):
    """[(wall_s, value)] from curve points with ``feature_<key>``, else the final eval point."""
    pts = [(p["wall_s"], p[f"feature_{key}"]) for p in record["curve"]
           if _num(p.get("wall_s")) is not None and _num(p.get(f"feature_{key}")) is not None]
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
    axes[1].set(ylabel="feature L2 error", xlabel="training wall-clock time (s)")
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


def write_report(records, out_dir) -> dict[str, Path]:
    """Write the table and plots for ``records`` (from :func:`collect`) into ``out_dir``.

    Returns ``{file name: path}`` of what was written; ``feature_error_vs_time.png`` is missing
    from it (and a stale copy removed) when no run has feature metrics.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keys, fixed = swept_keys(records)
    written = {name: out / name for name in ("report.md", "report.csv")}
    written["report.md"].write_text(render_markdown(records, keys, fixed))
    _write_csv(records, keys, written["report.csv"])

    cmap = plt.get_cmap("tab10" if len(records) <= 10 else "tab20")
    runs = [(r, f"{r['job']}: {run_label(r, keys)}" + (" (incomplete)" if r["status"] == "incomplete" else ""),
             cmap(i % cmap.N)) for i, r in enumerate(records) if not r["status"].startswith("failed")]
    for name, plot in (("psnr_vs_time.png", _plot_psnr_vs_time), ("psnr_vs_size.png", _plot_psnr_vs_size),
                       ("anchors_vs_step.png", _plot_anchors)):
        plot(runs, out / name)
        written[name] = out / name
    feature_path = out / "feature_error_vs_time.png"
    if _plot_features(runs, feature_path):
        written[feature_path.name] = feature_path
    else:
        feature_path.unlink(missing_ok=True)
    return written


# ----------------------------------------------------------------------------- command line


def main(argv=None) -> int:
    """``cusgs-report <root> [--out DIR]``: print the Markdown table and write the report files."""
    parser = argparse.ArgumentParser(prog="cusgs-report", description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="Hydra multirun folder (made by `cusgs-train -m ...`)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: <root>/report)")
    args = parser.parse_args(argv)
    expected = ("expected a Hydra multirun folder made by `cusgs-train -m ...`, with job folders "
                "(0/, 1/, ...) holding .hydra/config.yaml, eval.json or failed.json")
    if not args.root.is_dir():
        parser.error(f"{args.root} does not exist or is not a folder; {expected}")
    records = collect(args.root)
    if not records:
        parser.error(f"no job folders found in {args.root}; {expected}")
    written = write_report(records, args.out or args.root / "report")
    print(written["report.md"].read_text())
    if "feature_error_vs_time.png" not in written:
        print("no run has feature metrics: skipped feature_error_vs_time.png")
    print("wrote " + ", ".join(str(p) for p in written.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
