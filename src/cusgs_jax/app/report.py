"""``cusgs-report``: one table and a few plots for a Hydra sweep made by ``cusgs-train -m ...``.

Usage: ``cusgs-report <multirun folder> [--out DIR]``.

Input. A *job folder* is any folder under the multirun folder that holds ``.hydra/config.yaml``,
``eval.json`` or ``failed.json`` (Hydra numbers them ``0/``, ``1/``, ...). What is read from it:

* ``.hydra/overrides.yaml`` -- the job's command-line overrides (``["prune.ratio=0.01", ...]``).
* ``eval.json`` -- written when a run finishes: ``psnr``, ``ssim``, ``params`` (``total`` and its
  parts), ``alive_anchors``, ``prune`` (``passes``, ``pruned``), ``time`` (``train_steps``, ``densify``,
  ``compile_wait``, ``total``), ``compilations``, ``train_wall_s``, ``render_ms_per_view``, ``model_bytes``,
  ``checkpoint_bytes``,
  optional ``lpips_vgg`` / ``lpips_alex`` (the lpips extra), ``render_ms_before_prune``,
  ``ply_bytes``, ``features.models.<name>.{cosine,l2}`` and the held-out ``curve``.
* ``*.ply`` -- an exported PLY in the job folder gives Table 1's PLY size (its model size is ``model_bytes``).
* ``eval_curve.jsonl`` -- the held-out curve so far (used while a run is still going).
* ``metrics.jsonl`` -- training log rows; ``step`` and ``alive_anchors`` are used.
* ``failed.json`` -- ``{"error": "Type: message", "traceback": ...}`` when the job raised.

A job is ``ok`` (has ``eval.json``), ``failed: <first error line>`` (has ``failed.json``, or an
``eval.json`` that cannot be read) or ``incomplete`` (neither: still running or killed).

Output, in ``<root>/report/`` unless ``--out`` says otherwise:

* ``report.md`` -- the table (CUS-GS Table 4 style, rounded) and a line naming the best-PSNR and
  the smallest run, then a Table-1 style table (model MB, PLY MB, parameters, PSNR, SSIM, LPIPS) and a
  Table-2 style table (per feature model cosine / L2 distance, parameter split;
  :mod:`cusgs_jax.app.paper_tables`); also printed to stdout. Where two finished jobs say how long they
  compiled, a line names the spread (the jobs that run first compile what later jobs load from the
  persistent compilation cache) and points to ``steps (s)``, the training time without compiles. When
  ``train.seed`` is swept, a table gives mean ± sample std over the jobs that differ only in it
  (:func:`seed_summary`).
  Its ``Pareto`` column marks (★) the non-dominated runs: no other finished run has at least the
  held-out PSNR with at most the parameters, one of them strictly (:func:`mark_pareto`).
* ``report.csv`` -- the Table-4 rows at full precision with one column per swept override key,
  ``pareto`` (1 on the front, 0 off it, empty without both numbers), plus ``lpips_vgg``, ``lpips_alex``, ``size_mb`` (the model: ``model_bytes``), ``size_of`` (``model``, or ``checkpoint`` for a run older than
  ``model_bytes``) and ``ply_mb``.
* ``psnr_vs_time.png`` -- held-out PSNR against the training clock's seconds, one line per run: the loop's
  steps and densification with the compiles it waited for after its first step, not the first step's
  compile (:data:`cusgs_jax.eval.plots.CLOCK`).
* ``feature_error_vs_time.png`` -- feature cosine distance and L2 error against the training clock's
  seconds; not written when no run evaluated feature fields.
* ``psnr_vs_size.png`` -- final PSNR against total parameters, Pareto front highlighted.
* ``psnr_vs_job_time.png`` -- final PSNR against the whole job's seconds (``time.total``, compiles included).
* ``anchors_vs_step.png`` -- alive anchors against training step, one line per run.

Failed jobs are listed in the table but left out of the plots; incomplete jobs are plotted with
dashed lines from their partial logs.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import os
import re
import sys
from pathlib import Path

import yaml

from cusgs_jax.errors import UserError
from cusgs_jax.run_folder import CURVE_FILE, EVAL_FILE, FAILED_FILE, HYDRA_DIR, METRICS_FILE, read_eval
from cusgs_jax.app.paper_tables import CSV_COLUMNS, paper_fields, table1_markdown, table2_markdown
from cusgs_jax.eval.sweep_plots import finite_or_none, pareto_front, write_plots

#: Metric columns: (record / CSV key, Markdown header, Markdown format, meaning).
METRICS = [
    ("dataset_format", "format", "{}", "the scene's layout: colmap, blender or nerfstudio (eval.json dataset_format; "
     "Blender scenes are evaluated on their test split, the others on every 8th image)"),
    ("params", "params", "{:,.0f}", "total trained parameters (eval.json params.total)"),
    ("anchors", "anchors", "{:,.0f}", "alive anchors at the end of training"),
    ("passes", "passes", "{:,.0f}", "feature-aware pruning passes run (eval.json prune.passes, what the strategy's "
     "results record; 0 without feature-aware pruning or when its schedule never ran)"),
    ("pruned", "pruned", "{:,.0f}", "anchors those passes removed (eval.json prune.pruned)"),
    ("ssim", "SSIM", "{:.4f}", "held-out SSIM"),
    ("psnr", "PSNR", "{:.2f}", "held-out PSNR in dB"),
    ("feature_cosine", "feat. cos", "{:.4f}",
     "cosine distance 1-cos of the rendered feature maps, mean over feature models (lower is better)"),
    ("feature_l2", "feat. L2", "{:.4f}", "L2 error of the rendered feature maps, mean over feature models"),
    ("train_s", "train (s)", "{:.1f}", "the training clock's seconds (eval.json train_wall_s, the x axis of "
     "psnr_vs_time.png): steps and densification, with the compiles the loop waited for after its first step; the "
     "first step's compile, evaluation and checkpoints not (eval/plots.py CLOCK)"),
    ("steps_s", "steps (s)", "{:.1f}", "training steps and densification with no compile at all (eval.json "
     "time.train_steps + time.densify; every wait for a compiler is in compile wait): the time to compare between "
     "jobs, which train (s) and run (s) are not when the jobs run first compile what later ones load from the "
     "persistent compilation cache"),
    ("run_s", "run (s)", "{:.1f}", "the whole run's seconds: load, features, PSC, compiling, training, "
     "evaluation, checkpoints, report (eval.json time.total; the x axis of psnr_vs_job_time.png)"),
    ("compile_s", "compile (s)", "{:.1f}", "seconds spent compiling XLA programs, tracing included, those compiled "
     "ahead on the background thread too (eval.json compilations.seconds; small when the persistent compilation "
     "cache held them)"),
    ("compile_wait_s", "compile wait (s)", "{:.1f}", "seconds the run stood still for a compiler: compiles on its "
     "own thread and waits for a program still compiling ahead (eval.json time.compile_wait; absent before it)"),
    ("render_ms", "render ms/view", "{:.1f}", "median held-out render time per view"),
    ("render_ms_before_prune", "render ms/view at 1st prune", "{:.1f}",
     "render time per view of the model just before the first pruning pass (pruning runs only; it has "
     "fewer anchors than the final model when growing continues afterwards)"),
]
MARKERS = (".hydra/config.yaml", EVAL_FILE, FAILED_FILE)


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
    if rows and all(finite_or_none(r.get("step")) is not None for r in rows):
        rows = sorted({r["step"]: r for r in rows}.values(), key=lambda r: r["step"])
    return rows


def _read_overrides(job: Path) -> dict[str, str | None]:
    """``{"prune.ratio": "0.01", ...}`` from ``.hydra/overrides.yaml`` (leading ``+`` dropped)."""
    try:
        items = yaml.safe_load((job / HYDRA_DIR / "overrides.yaml").read_text())
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
    values = [v for v in map(finite_or_none, values) if v is not None]
    return sum(values) / len(values) if values else None


def _eval_metrics(result: dict) -> dict:
    """The metric columns (see :data:`METRICS`) from a parsed ``eval.json``."""
    params = result.get("params")
    features = result.get("features")
    models = features.get("models") if isinstance(features, dict) else None
    models = [m for m in models.values() if isinstance(m, dict)] if isinstance(models, dict) else []
    layout = result.get("dataset_format")
    time = result.get("time") if isinstance(result.get("time"), dict) else {}
    passes, pruned = _pruning(result)
    return {
        "dataset_format": layout if isinstance(layout, str) else None,
        "params": finite_or_none(params.get("total")) if isinstance(params, dict) else finite_or_none(params),
        "anchors": finite_or_none(result.get("alive_anchors")),
        "passes": passes,
        "pruned": pruned,
        "ssim": finite_or_none(result.get("ssim")),
        "psnr": finite_or_none(result.get("psnr")),
        "feature_cosine": _mean(m.get("cosine") for m in models),
        "feature_l2": _mean(m.get("l2") for m in models),
        "train_s": finite_or_none(result.get("train_wall_s")),
        "steps_s": _seconds(time, "train_steps", "densify"),
        "run_s": finite_or_none(time.get("total")),
        "compile_s": finite_or_none(c.get("seconds")) if isinstance(c := result.get("compilations"), dict) else None,
        "compile_wait_s": finite_or_none(time.get("compile_wait")),
        "render_ms": finite_or_none(result.get("render_ms_per_view")),
        "render_ms_before_prune": finite_or_none(result.get("render_ms_before_prune")),
    }


def _pruning(result) -> tuple[float | None, float | None]:
    """(passes, pruned) of feature-aware pruning: the ``prune`` block its results fill in (densify/feature_prune.py
    ``results``), else its tally in ``densify`` (``updates``, ``pruned``); None where neither says."""
    block = result.get("prune")
    block = block if isinstance(block, dict) else {}
    densify = result.get("densify")
    tally = densify.get("feature_prune") if isinstance(densify, dict) else None
    tally = tally if isinstance(tally, dict) else {}
    passes = finite_or_none(block.get("passes"))
    pruned = finite_or_none(block.get("pruned"))
    return (finite_or_none(tally.get("updates")) if passes is None else passes,
            finite_or_none(tally.get("pruned")) if pruned is None else pruned)


def _seconds(time: dict, *stages: str) -> float | None:
    """The sum of ``time``'s ``stages`` (those present), None when the first is missing."""
    if finite_or_none(time.get(stages[0])) is None:
        return None
    return sum(finite_or_none(time.get(stage)) or 0.0 for stage in stages)


def _newer(a: Path, b: Path) -> bool:
    """Whether file ``a`` exists and was written after ``b`` (a job rerun that finished after a failure)."""
    try:
        return a.is_file() and a.stat().st_mtime > b.stat().st_mtime
    except OSError:
        return False


def load_job(path, root=None) -> dict:
    """One record for one job folder.

    Keys: ``job`` (path relative to ``root``, or the folder name), ``path``, ``overrides``
    (key -> value string), ``status``, the :data:`METRICS` keys (float or None; None unless
    ``ok``), the :func:`~cusgs_jax.app.paper_tables.paper_fields` keys (Tables 1 and 2), ``curve`` (held-out points ``{"step", "wall_s", "psnr", ...}``) and ``anchor_curve``
    (``[(step, alive_anchors), ...]`` from ``metrics.jsonl``).
    """
    path = Path(path)
    record = dict(job=path.relative_to(root).as_posix() if root is not None else path.name,
                  path=path, overrides=_read_overrides(path), status="incomplete",
                  **{key: None for key, *_ in METRICS}, **{key: None for key in CSV_COLUMNS},
                  param_split={}, feature_models={})
    record["curve"] = _read_jsonl(path / CURVE_FILE)
    record["anchor_curve"] = [(r["step"], r["alive_anchors"]) for r in _read_jsonl(path / METRICS_FILE)
                              if finite_or_none(r.get("step")) is not None
                              and finite_or_none(r.get("alive_anchors")) is not None]
    if (path / FAILED_FILE).is_file() and not _newer(path / EVAL_FILE, path / FAILED_FILE):
        try:
            error = json.loads((path / FAILED_FILE).read_text()).get("error") or "unknown error"
        except (OSError, ValueError, AttributeError) as exc:
            error = f"unreadable {FAILED_FILE} ({type(exc).__name__}: {_first_line(exc)})"
        record["status"] = "failed: " + _first_line(error)
    elif (path / EVAL_FILE).is_file():
        try:
            result = read_eval(path)  # the run-folder contract (run_folder.py)
        except UserError as exc:  # damaged (the JSON error is its cause), newer, or holding a key it may not
            cause = exc.__cause__
            why = f"{type(cause).__name__}: {_first_line(cause)}" if cause is not None else _first_line(exc)
            record["status"] = f"failed: unreadable {EVAL_FILE} ({why})"
        else:
            record.update(_eval_metrics(result), **paper_fields(result, path), status="ok")
            curve = [p for p in result.get("curve") or [] if isinstance(p, dict)]
            record["curve"] = curve or record["curve"]
    return record


def collect(root) -> list[dict]:
    """:func:`load_job` for every job folder under ``root``."""
    return [load_job(job, root) for job in find_jobs(root)]


# ----------------------------------------------------------------------------- summarising


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


def mark_pareto(records) -> list[dict]:
    """Set ``record["pareto"]``: True for the finished runs no other run beats in both held-out PSNR
    (higher) and parameter count (lower) (:func:`~cusgs_jax.eval.sweep_plots.pareto_front`), False
    for the other finished runs, None for runs without both numbers. Returns the front, smallest first."""
    ok = [r for r in records if r["status"] == "ok" and r["psnr"] is not None and r["params"] is not None]
    for r in records:
        r["pareto"] = None
    front = pareto_front([(r["params"], r["psnr"]) for r in ok])
    for i, r in enumerate(ok):
        r["pareto"] = i in front
    return [ok[i] for i in front]


def run_label(record, keys) -> str:
    """``"prune.ratio=0.01, prune.passes=10"`` from the swept ``keys``; ``"(defaults)"`` if none."""
    parts = [k if record["overrides"][k] is None else f"{k}={record['overrides'][k]}"
             for k in keys if k in record["overrides"]]
    return ", ".join(parts) or "(defaults)"


def _cell(value, fmt) -> str:
    return "" if value is None else fmt.format(value)


def render_markdown(records, keys, fixed) -> str:
    """The Markdown report: header, table (one row per job), the best / smallest line, Tables 1 and 2."""
    counts = {s: sum(r["status"].split(":")[0] == s for r in records) for s in ("ok", "failed", "incomplete")}
    lines = ["# Sweep report", "",
             f"{len(records)} jobs: {counts['ok']} ok, {counts['failed']} failed, {counts['incomplete']} incomplete."]
    if fixed:
        lines.append("Shared overrides: " + ", ".join(f"`{o}`" for o in fixed) + ".")
    front = mark_pareto(records)
    header = ["job", "run", "status", "Pareto"] + [h for _, h, *_ in METRICS]
    lines += ["", "## Table 4 style: every job", "",
              "Pareto: ★ marks the runs on the front of held-out PSNR (higher) against parameters (lower): "
              "no other run has both at least as many dB and at most as many parameters, one of them strictly.",
              "", "| " + " | ".join(header) + " |",
              "|" + "|".join(["---"] * 4 + [":---" if fmt == "{}" else "---:" for _, _, fmt, _ in METRICS]) + "|"]
    for r in records:
        status = r["status"] if len(r["status"]) <= 120 else r["status"][:117] + "..."
        cells = [r["job"], run_label(r, keys), status, "★" if r.get("pareto") else ""] + \
            [_cell(r[k], fmt) for k, _, fmt, _ in METRICS]
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
    if front:
        lines.append(f"Pareto front ({len(front)} of {len(records)} runs, smallest first): " + "; ".join(
            f"job `{r['job']}` {r['psnr']:.2f} dB / {r['params']:,.0f} params" for r in front) + ".")
    lines += _compile_bias(ok)
    lines += _seeds_markdown(seed_summary(records, keys))
    label = functools.partial(run_label, keys=keys)
    lines += [""] + table1_markdown(records, label) + [""] + table2_markdown(records, label)
    return "\n".join(lines) + "\n"


def _compile_bias(ok) -> list[str]:
    """The line that says which time columns carry compiles, and how unevenly the finished jobs paid them."""
    compiled = sorted((r["compile_s"], r["job"]) for r in ok if r["compile_s"] is not None)
    if len(compiled) < 2:
        return []
    (low, low_job), (high, high_job) = compiled[0], compiled[-1]
    return ["", f"Times: `train (s)`, `run (s)` and psnr_vs_job_time.png include compiling, which the jobs do not pay "
                f"alike: the jobs that run first compile programs that later jobs load from the persistent "
                f"compilation cache (`compile (s)` from {low:.1f} s in job `{low_job}` to {high:.1f} s in job "
                f"`{high_job}`). Compare jobs by `steps (s)`, which leaves every compile out."]


#: The override key of the seed: jobs differing only in it are repeats of one setting.
SEED_KEY = "train.seed"


def _mean_std(values) -> tuple[float, float] | None:
    """(mean, sample standard deviation) of the finite ``values``; None for fewer than two."""
    values = [v for v in map(finite_or_none, values) if v is not None]
    if len(values) < 2:
        return None
    mean = sum(values) / len(values)
    return mean, (sum((v - mean) ** 2 for v in values) / (len(values) - 1)) ** 0.5


#: The columns :func:`seed_summary` averages: (record key, Markdown header, format).
SEED_COLUMNS = (("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("params", "params", "{:,.0f}"),
                ("anchors", "anchors", "{:,.0f}"), ("steps_s", "steps (s)", "{:.1f}"))


def seed_summary(records, keys) -> list[dict]:
    """Mean ± std over the finished jobs that differ only in ``train.seed``: one dict per setting run with two or
    more seeds, ``{"label", "jobs", "seeds", <column>: (mean, std) or None}`` for :data:`SEED_COLUMNS`, in the
    order of the settings' first jobs. Empty when the seed is not swept."""
    if SEED_KEY not in keys:
        return []
    others = [k for k in keys if k != SEED_KEY]
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        if r["status"] == "ok":
            groups.setdefault(tuple(r["overrides"].get(k) for k in others), []).append(r)
    summary = []
    for group in groups.values():
        if len({r["overrides"].get(SEED_KEY) for r in group}) < 2:
            continue
        summary.append(dict(label=run_label(group[0], others), jobs=[r["job"] for r in group],
                            seeds=[r["overrides"].get(SEED_KEY) for r in group],
                            **{key: _mean_std(r[key] for r in group) for key, *_ in SEED_COLUMNS}))
    return summary


def _seeds_markdown(summary) -> list[str]:
    if not summary:
        return []
    header = ["run", "jobs", "seeds"] + [h for _, h, _ in SEED_COLUMNS]
    lines = ["", "## Over seeds: mean ± std", "",
             f"Finished jobs that differ only in `{SEED_KEY}`, as mean ± sample standard deviation.", "",
             "| " + " | ".join(header) + " |", "|" + "|".join([":---"] * 3 + ["---:"] * len(SEED_COLUMNS)) + "|"]
    for row in summary:
        cells = [row["label"], ", ".join(f"`{j}`" for j in row["jobs"]), ", ".join(map(str, row["seeds"]))]
        cells += ["" if row[key] is None else f"{fmt.format(row[key][0])} ± {fmt.format(row[key][1])}"
                  for key, _, fmt in SEED_COLUMNS]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return lines


def _write_csv(records, keys, path: Path) -> None:
    """``job``, one column per swept key, ``status``, the :data:`METRICS`, then LPIPS and size (full precision)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["job", *keys, "status", "pareto", *(k for k, *_ in METRICS), *CSV_COLUMNS])
        mark_pareto(records)
        for r in records:
            sweeps = [r["overrides"].get(k) or "" for k in keys]
            values = ["" if r[k] is None else (int(r[k]) if k in ("params", "anchors", "passes", "pruned") else r[k])
                      for k, *_ in METRICS]
            extra = ["" if r[k] is None else r[k] for k in CSV_COLUMNS]
            pareto = "" if r["pareto"] is None else int(r["pareto"])
            writer.writerow([r["job"], *sweeps, r["status"], pareto, *values, *extra])


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
    labels = [f"{r['job']}: {run_label(r, keys)}" for r in records]
    written.update(write_plots(records, labels, out))
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
