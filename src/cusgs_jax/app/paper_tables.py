"""The CUS-GS paper's Table-1 and Table-2 style tables of a sweep, for ``cusgs-report``.

* Table 1 (novel-view synthesis and size): one row per finished run — the model's size in MB
  (``eval.json`` ``model_bytes``: parameters and PSC banks, no optimiser state), the exported
  PLY's size in MB when the job folder has one, trained parameters, PSNR, SSIM and LPIPS (VGG;
  AlexNet in the CSV).
* Table 2 (feature fields): one row per finished run that trained feature fields — the cosine
  and L2 distance of each feature model's rendered maps (a column pair per model, as the paper
  lays out its foundation models side by side), then the parameter split of ``eval.json``'s
  ``params`` (anchors, MLPs, appearance, query heads, memory banks, memory adapters, total).

:func:`paper_fields` reads what these tables need from a parsed ``eval.json`` and the job folder;
the record keys it returns are documented there.
"""

from __future__ import annotations

from pathlib import Path

from cusgs_jax.eval.sweep_plots import finite_or_none

__all__ = ["CSV_COLUMNS", "PARAM_PARTS", "paper_fields", "table1_markdown", "table2_markdown"]

#: Columns added to ``report.csv`` (record keys).
CSV_COLUMNS = ("lpips_vgg", "lpips_alex", "size_mb", "size_of", "ply_mb")

#: ``eval.json`` ``params`` parts in Table-2 order, with their headers.
PARAM_PARTS = (("anchors", "anchors"), ("mlps", "MLPs"), ("appearance", "appearance"),
               ("query_heads", "query heads"), ("memory_banks", "memory banks"), ("adapters", "adapters"),
               ("total", "total"))


def _ply_bytes(result: dict, job: Path) -> int | None:
    """Size of the run's exported PLY: ``eval.json`` ``ply_bytes``, else the newest ``*.ply`` in the job folder."""
    size = finite_or_none(result.get("ply_bytes"))
    if size is not None:
        return int(size)
    plies = [p for p in job.rglob("*.ply") if p.is_file()] if job.is_dir() else []
    return max(plies, key=lambda p: p.stat().st_mtime).stat().st_size if plies else None


def paper_fields(result: dict, job: Path) -> dict:
    """Record keys for Tables 1 and 2 from a parsed ``eval.json`` of the job folder ``job``.

    Returns:
      {"lpips_vgg", "lpips_alex": float or None (absent without the lpips extra),
       "size_mb": ``model_bytes`` / 1e6 (the trained parameters and PSC banks, no optimiser state),
       else — a run older than ``model_bytes`` — ``checkpoint_bytes`` / 1e6, or None,
       "size_of": "model" | "checkpoint" | None,
       "ply_mb": the exported PLY's bytes / 1e6 (``ply_bytes``, else the newest ``*.ply`` in the job folder), or None,
       "param_split": {part: count} (keys of :data:`PARAM_PARTS` present in ``params``),
       "feature_models": {model: {"cosine", "l2"}} (floats or None; empty without features)}.
    """
    ply = _ply_bytes(result, job)
    model = finite_or_none(result.get("model_bytes"))
    ckpt = finite_or_none(result.get("checkpoint_bytes"))
    size_mb, size_of = (model / 1e6, "model") if model is not None else (
        (ckpt / 1e6, "checkpoint") if ckpt is not None else (None, None))
    params = result.get("params")
    split = {k: finite_or_none(params.get(k)) for k, _ in PARAM_PARTS} if isinstance(params, dict) else {}
    features = result.get("features")
    models = features.get("models") if isinstance(features, dict) else None
    feature_models = {str(name): {"cosine": finite_or_none(m.get("cosine")), "l2": finite_or_none(m.get("l2"))}
                      for name, m in (models.items() if isinstance(models, dict) else ()) if isinstance(m, dict)}
    return dict(lpips_vgg=finite_or_none(result.get("lpips_vgg")), lpips_alex=finite_or_none(result.get("lpips_alex")),
                size_mb=size_mb, size_of=size_of, ply_mb=None if ply is None else ply / 1e6, param_split={k: v for k, v in split.items() if v is not None},
                feature_models=feature_models)


def _cell(value, fmt: str) -> str:
    return "" if value is None else fmt.format(value)


def _row(cells) -> str:
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def table1_markdown(records, label) -> list[str]:
    """Lines of the Table-1 style table (finished runs only); ``label(record)`` names a run."""
    ok = [r for r in records if r["status"] == "ok"]
    lines = ["## Table 1 style: size and image quality", ""]
    if not ok:
        return lines + ["No job has finished yet."]
    lines += [_row(["job", "run", "model (MB)", "PLY (MB)", "parameters", "PSNR", "SSIM", "LPIPS (VGG)"]),
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in ok:
        size = _cell(r.get("size_mb"), "{:.2f}") + (" (ckpt)" if r.get("size_of") == "checkpoint" else "")
        lines.append(_row([r["job"], label(r), size, _cell(r.get("ply_mb"), "{:.2f}"), _cell(r["params"], "{:,.0f}"),
                           _cell(r["psnr"], "{:.2f}"), _cell(r["ssim"], "{:.4f}"), _cell(r.get("lpips_vgg"), "{:.4f}")]))
    notes = ["model (MB): the trained parameters and PSC banks (eval.json model_bytes; no optimiser state), in "
             "10^6 bytes; a run older than model_bytes shows its final checkpoint instead, marked \"(ckpt)\" (it "
             "also holds the Adam moments). PLY (MB): the exported standard 3DGS PLY (cusgs-export) when the job "
             "folder has one."]
    if any(r.get("lpips_vgg") is None for r in ok):
        notes.append("A blank LPIPS: the run had no lpips extra (pip install -e '.[lpips]') or views too small.")
    return lines + [""] + notes


def table2_markdown(records, label) -> list[str]:
    """Lines of the Table-2 style table: finished runs with feature fields; ``label(record)`` names a run."""
    rows = [r for r in records if r["status"] == "ok" and r.get("feature_models")]
    lines = ["## Table 2 style: feature fields and parameter split", ""]
    if not rows:
        return lines + ["No finished run evaluated feature fields."]
    models = list(dict.fromkeys(m for r in rows for m in r["feature_models"]))
    parts = [(k, h) for k, h in PARAM_PARTS if any(k in r.get("param_split", {}) for r in rows)]
    header = ["job", "run"] + [f"{m} {what}" for m in models for what in ("cos", "L2")] + [h for _, h in parts]
    lines += [_row(header), "|" + "|".join(["---"] * 2 + ["---:"] * (len(header) - 2)) + "|"]
    for r in rows:
        cells = [r["job"], label(r)]
        for m in models:
            vals = r["feature_models"].get(m, {})
            cells += [_cell(vals.get("cosine"), "{:.4f}"), _cell(vals.get("l2"), "{:.4f}")]
        cells += [_cell(r["param_split"].get(k), "{:,.0f}") for k, _ in parts]
        lines.append(_row(cells))
    return lines + ["", "cos: cosine distance 1 − cos, L2: L2 distance of the rendered feature maps on held-out "
                        "views (lower is better); parameters by part, memory banks = PSC entries, adapters = "
                        "memory heads."]
