"""``cusgs-report`` on a synthetic Hydra multirun folder (no training)."""

from __future__ import annotations

import csv
import json

import pytest
import yaml
from PIL import Image

from cusgs_jax.app.report import collect, find_jobs, load_job, main, mark_pareto

PLOTS = ("psnr_vs_time.png", "feature_error_vs_time.png", "psnr_vs_size.png", "anchors_vs_step.png",
         "psnr_vs_job_time.png")


def _job(root, name, ratio, *, extra=()):
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    overrides = ["experiment=prune_ratio", f"prune.ratio={ratio}", "seed=0", *extra]
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"prune": {"ratio": ratio}, "seed": 0}))
    return job


def _jsonl(path, rows, tail=""):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + tail)


def _eval(job, psnr, ssim, total, anchors, wall, ms, *, before=None, features=None, curve=None, lpips=None,
          ckpt_bytes=None, model_bytes=None):
    params = {"anchors": total // 2, "mlps": total // 4, "appearance": 0, "query_heads": 0,
              "memory_banks": 0, "adapters": 0, "total": total}
    curve = curve or [{"step": 100, "wall_s": wall / 2, "psnr": psnr - 3, "ssim": ssim - 0.1},
                      {"step": 200, "wall_s": wall, "psnr": psnr, "ssim": ssim}]
    result = {"psnr": psnr, "ssim": ssim, "alive_anchors": anchors, "capacity": 4096, "train_wall_s": wall,
              "render_ms_per_view": ms, "params": params, "curve": curve}
    if before is not None:
        result["render_ms_before_prune"] = before
        result["prune"] = {"strategy": "feature_aware", "passes": 10, "pruned": 123}
    if features is not None:
        result["features"] = {"models": features, "markdown": "..."}
    if lpips is not None:
        result["lpips_vgg"], result["lpips_alex"] = lpips
    if ckpt_bytes is not None:
        result["checkpoint_bytes"] = ckpt_bytes
    if model_bytes is not None:
        result["model_bytes"] = model_bytes
    (job / "eval.json").write_text(json.dumps(result))
    _jsonl(job / "metrics.jsonl", [{"step": s, "wall_s": s / 10, "loss": 0.1, "alive_anchors": 1000 - s}
                                   for s in (10, 100, 200)])


@pytest.fixture
def sweep(tmp_path):
    """Five jobs: two ok (one with feature curves), failed, incomplete, unreadable eval.json."""
    root = tmp_path / "multirun" / "12-00-00"
    root.mkdir(parents=True)
    (root / "multirun.yaml").write_text("hydra: {mode: MULTIRUN}\n")
    feats = {"clip": {"cosine": 0.2, "l2": 1.0, "baseline_cosine": 0.1, "baseline_l2": 0.5},
             "dino": {"cosine": 0.4, "l2": 3.0, "baseline_cosine": 0.1, "baseline_l2": 0.5}}
    curve = [{"step": 100, "wall_s": 5.0, "psnr": 22.0, "ssim": 0.7,
              "feature_cosine": 0.5, "feature_l2": 4.0},
             {"step": 200, "wall_s": 10.25, "psnr": 25.123456789, "ssim": 0.8123456,
              "feature_cosine": 0.3, "feature_l2": 2.0}]
    _eval(_job(root, "0", 0.01), 25.123456789, 0.8123456, 200_000, 900, 10.25, 3.3333,
          before=4.75, features=feats, curve=curve, lpips=(0.123456789, 0.0456), ckpt_bytes=12_345_678)
    job1 = _job(root, "1", 0.1)
    _eval(job1, 26.5, 0.85, 3_000_000, 5000, 20.0, 7.5, features={"clip": {"cosine": 0.25, "l2": 1.5}},
          ckpt_bytes=99_000_000, model_bytes=12_000_000)
    (job1 / "export").mkdir()
    (job1 / "export" / "point_cloud.ply").write_bytes(b"x" * 2_500_000)  # shown beside the model's size
    failed = _job(root, "2", 0.2)
    (failed / "failed.json").write_text(json.dumps(
        {"error": "FloatingPointError: NaN loss at step 7\nsecond line", "traceback": "Traceback ..."}))
    _jsonl(failed / "eval_curve.jsonl", [{"step": 100, "wall_s": 3.0, "psnr": 12.0, "ssim": 0.3}])
    running = _job(root, "3", 0.3)
    _jsonl(running / "eval_curve.jsonl", [{"step": 100, "wall_s": 4.0, "psnr": 20.0, "ssim": 0.6}],
           tail='{"step": 2')  # a half-written last line
    _jsonl(running / "metrics.jsonl", [{"step": 10, "wall_s": 0.4, "alive_anchors": 800}])
    broken = _job(root, "10", 0.5)
    (broken / "eval.json").write_text('{"psnr": 30.0,')
    return root


def _csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_report_end_to_end(sweep, capsys):
    assert main([str(sweep)]) == 0
    out = sweep / "report"
    rows = _csv_rows(out / "report.csv")
    assert [r["job"] for r in rows] == ["0", "1", "2", "3", "10"]  # natural order
    assert "prune.ratio" in rows[0] and "experiment" not in rows[0] and "seed" not in rows[0]
    assert [r["prune.ratio"] for r in rows] == ["0.01", "0.1", "0.2", "0.3", "0.5"]
    assert [r["status"] for r in rows[:4]] == ["ok", "ok", "failed: FloatingPointError: NaN loss at step 7",
                                               "incomplete"]
    assert rows[4]["status"].startswith("failed: unreadable eval.json (JSONDecodeError")

    first = rows[0]
    assert float(first["psnr"]) == 25.123456789 and float(first["ssim"]) == 0.8123456
    assert int(first["params"]) == 200_000 and int(first["anchors"]) == 900
    assert float(first["train_s"]) == 10.25 and float(first["render_ms"]) == 3.3333
    assert float(first["render_ms_before_prune"]) == 4.75
    assert float(first["feature_cosine"]) == pytest.approx(0.3) and float(first["feature_l2"]) == 2.0
    assert rows[1]["render_ms_before_prune"] == "" and float(rows[1]["feature_l2"]) == 1.5
    assert float(first["lpips_vgg"]) == 0.123456789 and float(first["lpips_alex"]) == 0.0456
    # job 0 predates model_bytes: its checkpoint stands in; job 1's size is the model's, its PLY beside it
    assert float(first["size_mb"]) == 12.345678 and first["size_of"] == "checkpoint" and first["ply_mb"] == ""
    assert rows[1]["lpips_vgg"] == rows[1]["lpips_alex"] == "" and rows[1]["size_of"] == "model"
    assert float(rows[1]["size_mb"]) == 12.0 and float(rows[1]["ply_mb"]) == 2.5
    assert [r["pareto"] for r in rows] == ["1", "1", "", "", ""]
    for row in rows[2:]:
        assert row["psnr"] == row["params"] == row["feature_cosine"] == row["lpips_vgg"] == row["size_mb"] == ""

    md = (out / "report.md").read_text()
    assert md in capsys.readouterr().out
    assert "`experiment=prune_ratio`" in md
    assert "| 0 | prune.ratio=0.01 | ok | ★ |  | 200,000 | 900 | 10 | 123 | 0.8123 | 25.12 |" in md
    assert "| 2 | prune.ratio=0.2 | failed: FloatingPointError: NaN loss at step 7 |  |" in md
    assert ("Pareto front (2 of 5 runs, smallest first): job `0` 25.12 dB / 200,000 params; "
            "job `1` 26.50 dB / 3,000,000 params.") in md
    assert "Best PSNR: job `1` (prune.ratio=0.1), 26.50 dB" in md
    assert "smallest model: job `0` (prune.ratio=0.01), 200,000 parameters" in md

    table1 = md.split("## Table 1 style")[1].split("## Table 2 style")[0]
    assert "| job | run | model (MB) | PLY (MB) | parameters | PSNR | SSIM | LPIPS (VGG) |" in table1
    assert "| 0 | prune.ratio=0.01 | 12.35 (ckpt) |  | 200,000 | 25.12 | 0.8123 | 0.1235 |" in table1
    assert "| 1 | prune.ratio=0.1 | 12.00 | 2.50 | 3,000,000 | 26.50 | 0.8500 |  |" in table1
    assert "no optimiser state" in table1
    assert "| 2 |" not in table1 and "no lpips extra" in table1  # finished runs only; blank LPIPS explained
    table2 = md.split("## Table 2 style")[1]
    assert ("| job | run | clip cos | clip L2 | dino cos | dino L2 | anchors | MLPs | appearance | query heads | "
            "memory banks | adapters | total |") in table2
    assert "| 0 | prune.ratio=0.01 | 0.2000 | 1.0000 | 0.4000 | 3.0000 | 100,000 | 50,000 | 0 | 0 | 0 | 0 | 200,000 |" \
        in table2
    assert "| 1 | prune.ratio=0.1 | 0.2500 | 1.5000 |  |  | 1,500,000 |" in table2

    for name in PLOTS:
        assert (out / name).stat().st_size > 0
        with Image.open(out / name) as image:
            image.verify()
            assert image.format == "PNG" and image.size == (960, 600 if name != PLOTS[1] else 840)


def test_records(sweep):
    assert [p.name for p in find_jobs(sweep)] == ["0", "1", "2", "3", "10"]
    records = {r["job"]: r for r in collect(sweep)}
    assert records["3"]["curve"] == [{"step": 100, "wall_s": 4.0, "psnr": 20.0, "ssim": 0.6}]  # torn line skipped
    assert records["3"]["anchor_curve"] == [(10, 800)]
    assert records["0"]["curve"][-1]["feature_cosine"] == 0.3
    assert load_job(sweep / "1")["job"] == "1"
    assert records["2"]["overrides"]["prune.ratio"] == "0.2"


def test_no_features_skips_plot_and_out_option(tmp_path, capsys):
    root = tmp_path / "sweep"
    _eval(_job(root, "0", 0.01), 24.0, 0.8, 1000, 10, 5.0, 1.0)
    _eval(_job(root, "1", 0.02, extra=["+model.extra=1"]), 23.0, 0.7, 500, 5, 4.0, 1.0)
    out = tmp_path / "elsewhere"
    out.mkdir()
    (out / "feature_error_vs_time.png").write_bytes(b"stale")
    main([str(root), "--out", str(out)])
    assert "skipped feature_error_vs_time.png" in capsys.readouterr().out
    assert not (out / "feature_error_vs_time.png").exists() and not (root / "report").exists()
    for name in set(PLOTS) - {"feature_error_vs_time.png"}:
        assert (out / name).stat().st_size > 0
    rows = _csv_rows(out / "report.csv")
    assert rows[0]["model.extra"] == "" and rows[1]["model.extra"] == "1"
    md = (out / "report.md").read_text()
    assert rows[0]["feature_cosine"] == "" and "| 0 | prune.ratio=0.01 | ok |" in md
    assert "No finished run evaluated feature fields." in md and rows[0]["size_mb"] == ""


def test_single_job_labels_defaults(tmp_path):
    _eval(_job(tmp_path, "0", 0.01), 24.0, 0.8, 1000, 10, 5.0, 1.0)
    main([str(tmp_path)])
    assert "| 0 | (defaults) | ok |" in (tmp_path / "report" / "report.md").read_text()


@pytest.mark.parametrize("make", ["missing", "empty", "file"])
def test_bad_root_exits_2(tmp_path, capsys, make):
    root = tmp_path / "not_a_sweep"
    if make == "empty":
        root.mkdir()
        (root / "notes.txt").write_text("hello")
    elif make == "file":
        root.write_text("x")
    with pytest.raises(SystemExit) as exc:
        main([str(root)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert str(root) in err and "cusgs-train -m" in err


def test_mark_pareto_matches_brute_force():
    """The report's front (``mark_pareto``) is exactly the set no other finished run dominates."""
    import random

    rng = random.Random(0)
    for _ in range(50):
        records = [dict(status=rng.choice(["ok", "ok", "ok", "failed: x", "incomplete"]),
                        params=float(rng.randint(1, 6)), psnr=float(rng.randint(20, 25))) for _ in range(rng.randint(0, 9))]
        front = mark_pareto(records)
        ok = [r for r in records if r["status"] == "ok"]
        for r in records:
            dominated = any(o["params"] <= r["params"] and o["psnr"] >= r["psnr"]
                            and (o["params"], o["psnr"]) != (r["params"], r["psnr"]) for o in ok)
            assert r["pareto"] == (None if r["status"] != "ok" else not dominated)
        assert [r["params"] for r in front] == sorted(r["params"] for r in front)
        assert {id(r) for r in front} == {id(r) for r in records if r["pareto"]}


def test_the_format_column_shows_each_runs_scene_layout(tmp_path):
    """eval.json's dataset_format reaches the Markdown table and the CSV; runs from before it existed show nothing."""
    root = tmp_path / "sweep"
    for name, layout in (("0", "blender"), ("1", "colmap"), ("2", None)):
        job = _job(root, name, 0.01 * (int(name) + 1))
        _eval(job, 24.0, 0.8, 1000, 10, 5.0, 1.0)
        if layout is not None:
            result = json.loads((job / "eval.json").read_text())
            (job / "eval.json").write_text(json.dumps(dict(result, dataset_format=layout, split="transforms_test")))
    main([str(root)])
    md = (root / "report" / "report.md").read_text()
    assert "| job | run | status | Pareto | format | params |" in md
    assert "| 0 | prune.ratio=0.01 | ok | ★ | blender | 1,000 |" in md
    assert [r["dataset_format"] for r in _csv_rows(root / "report" / "report.csv")] == ["blender", "colmap", ""]


def test_a_job_rerun_that_finished_after_its_failure_is_ok_and_a_later_failure_is_not(tmp_path):
    import os

    job = _job(tmp_path, "0", 0.01)
    (job / "failed.json").write_text(json.dumps({"error": "UserError: refused"}))
    _eval(job, 25.0, 0.8, 1000, 90, 10.0, 3.0)
    old = job.stat().st_mtime - 100
    os.utime(job / "failed.json", (old, old))  # the failure came first, the rerun's eval.json after it
    assert load_job(job)["status"] == "ok"
    os.utime(job / "eval.json", (old - 50, old - 50))  # now the failure is the newer record
    assert load_job(job)["status"] == "failed: UserError: refused"


def test_compile_seconds_and_the_seconds_waited_for_a_compiler_are_both_columns(tmp_path):
    job = _job(tmp_path, "0", 0.01)
    _eval(job, 25.0, 0.8, 1000, 90, 10.0, 3.0)
    record = json.loads((job / "eval.json").read_text())
    record.update(compilations={"seconds": 41.5, "count": 30}, time={"compile_wait": 2.25, "compile": 41.5})
    (job / "eval.json").write_text(json.dumps(record))
    row = load_job(job)
    assert (row["compile_s"], row["compile_wait_s"]) == (41.5, 2.25)


def _with(job, **keys):
    """Add ``keys`` to the job's eval.json."""
    record = json.loads((job / "eval.json").read_text())
    (job / "eval.json").write_text(json.dumps(dict(record, **keys)))


def test_pruning_passes_and_pruned_anchors_are_columns(tmp_path):
    root = tmp_path / "sweep"
    _eval(_job(root, "0", 0.01), 25.0, 0.8, 1000, 90, 10.0, 3.0, before=4.0)  # prune block: 10 passes, 123 pruned
    tallied = _job(root, "1", 0.02)  # a record whose prune block lacks them: the strategy's tally says
    _eval(tallied, 24.0, 0.8, 1000, 90, 10.0, 3.0)
    _with(tallied, prune={"strategy": "feature_aware"}, densify={"feature_prune": {"updates": 7, "pruned": 40}})
    none = _job(root, "2", 0.0)
    _eval(none, 24.0, 0.8, 1000, 90, 10.0, 3.0)
    _with(none, prune={"strategy": "none", "passes": 0, "pruned": 0})
    _eval(_job(root, "3", 0.03), 24.0, 0.8, 1000, 90, 10.0, 3.0)  # no record of pruning at all
    main([str(root)])
    rows = _csv_rows(root / "report" / "report.csv")
    assert [(r["passes"], r["pruned"]) for r in rows] == [("10", "123"), ("7", "40"), ("0", "0"), ("", "")]
    md = (root / "report" / "report.md").read_text()
    assert "| anchors | passes | pruned | SSIM |" in md and "| 90 | 10 | 123 | 0.8000 |" in md


def test_training_time_without_compiles_and_the_compile_bias_are_named(tmp_path):
    root = tmp_path / "sweep"
    for name, compiled, steps in (("0", 40.0, 12.5), ("1", 3.0, 11.0)):
        job = _job(root, name, 0.01 * (int(name) + 1))
        _eval(job, 25.0, 0.8, 1000, 90, 10.0, 3.0)
        _with(job, compilations={"seconds": compiled}, time={"train_steps": steps, "densify": 0.5,
                                                             "compile_wait": compiled / 2, "total": 60.0 + compiled})
    main([str(root)])
    rows = _csv_rows(root / "report" / "report.csv")
    assert [float(r["steps_s"]) for r in rows] == [13.0, 11.5]  # train_steps + densify: no compile in them
    assert [float(r["run_s"]) for r in rows] == [100.0, 63.0]
    md = (root / "report" / "report.md").read_text()
    assert ("the jobs that run first compile programs that later jobs load from the persistent compilation cache "
            "(`compile (s)` from 3.0 s in job `1` to 40.0 s in job `0`). Compare jobs by `steps (s)`") in md
    assert "| steps (s) |" in md


def test_a_single_job_has_no_compile_bias_line(tmp_path):
    job = _job(tmp_path, "0", 0.01)
    _eval(job, 25.0, 0.8, 1000, 90, 10.0, 3.0)
    _with(job, compilations={"seconds": 40.0})
    main([str(tmp_path)])
    assert "Compare jobs by" not in (tmp_path / "report" / "report.md").read_text()


def test_the_psnr_against_job_time_plot_shows_the_finished_jobs(tmp_path):
    from PIL import ImageChops

    images = {}
    for timed in (False, True):
        root = tmp_path / f"timed_{timed}"
        for name in ("0", "1"):
            job = _job(root, name, 0.01 * (int(name) + 1))
            _eval(job, 24.0 + int(name), 0.8, 1000, 90, 10.0, 3.0)
            if timed:
                _with(job, time={"total": 50.0 + 20 * int(name)})
        main([str(root)])
        assert load_job(root / "1")["run_s"] == (70.0 if timed else None)
        images[timed] = Image.open(root / "report" / "psnr_vs_job_time.png").convert("RGB")
    assert ImageChops.difference(images[False], images[True]).getbbox() is not None  # points, not "no data"


def test_jobs_that_differ_only_in_the_seed_are_summarised_as_mean_and_std(tmp_path):
    from cusgs_jax.app.report import seed_summary, swept_keys

    root = tmp_path / "sweep"
    runs = [("0", 0.01, 0, 25.0), ("1", 0.01, 1, 26.0), ("2", 0.01, 2, 27.0), ("3", 0.1, 0, 20.0),
            ("4", 0.1, 1, 22.0), ("5", 0.5, 0, 19.0)]
    for name, ratio, seed, psnr in runs:
        job = _job(root, name, ratio, extra=[f"train.seed={seed}"])
        _eval(job, psnr, 0.8, 1000 + 10 * seed, 90, 10.0, 3.0)
    records = collect(root)
    keys, _ = swept_keys(records)
    summary = seed_summary(records, keys)
    assert [(s["label"], s["jobs"], s["seeds"]) for s in summary] == [
        ("prune.ratio=0.01", ["0", "1", "2"], ["0", "1", "2"]), ("prune.ratio=0.1", ["3", "4"], ["0", "1"])]
    assert summary[0]["psnr"] == pytest.approx((26.0, 1.0)) and summary[1]["psnr"] == pytest.approx((21.0, 2 ** 0.5))
    assert summary[0]["params"] == pytest.approx((1010.0, 10.0)) and summary[0]["steps_s"] is None
    main([str(root)])
    md = (root / "report" / "report.md").read_text()
    assert "## Over seeds: mean ± std" in md
    assert "| prune.ratio=0.01 | `0`, `1`, `2` | 0, 1, 2 | 26.00 ± 1.00 | 0.8000 ± 0.0000 | 1,010 ± 10 |" in md
    assert "prune.ratio=0.5 |" not in md.split("## Over seeds")[1].split("##")[0]  # one seed: nothing to average
    assert seed_summary(collect(root), ["prune.ratio"]) == []  # the seed not swept: no summary


def test_a_negative_or_missing_time_in_eval_json_makes_the_job_unreadable_not_a_number(tmp_path):
    from cusgs_jax.run_folder import VERSION

    job = _job(tmp_path, "0", 0.01)
    _eval(job, 25.0, 0.8, 1000, 90, 10.0, 3.0)
    _with(job, time={"total": 60.0, "compile_wait": -5.0})
    row = load_job(job)
    assert row["status"].startswith("failed: unreadable eval.json (") and "time.compile_wait=-5.0" in row["status"]
    assert row["compile_wait_s"] is None
    record = json.loads((job / "eval.json").read_text())
    del record["time"]
    (job / "eval.json").write_text(json.dumps(dict(record, version=VERSION)))
    assert "'time' is missing" in load_job(job)["status"]
