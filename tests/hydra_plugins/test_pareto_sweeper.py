"""hydra_plugins/cusgs_pareto_sweeper (``hydra/sweeper=pareto``, ``experiment=pareto_search``): a tiny
search through the real ``cusgs-train`` command line writes pareto.json, each job returns (PSNR,
parameters), and ``cusgs-report`` marks the same front; bad sweeper settings exit 2 with one line."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

pytest.importorskip("optuna")  # the optuna extra


APP = [sys.executable, "-m", "cusgs_jax.app.train"]


@pytest.mark.slow  # a whole multi-job sweep / example run: .ci/run runs it with -m slow
def test_pareto_search_runs_through_the_cli_and_the_report_marks_its_front(tiny_sweep, tmp_path):
    sweep, (tiny_scene, tiny) = tmp_path / "pareto", tiny_sweep
    cmd = [*APP, "-m", "experiment=pareto_search", f"data.path={tiny_scene}", *tiny, "hydra.sweeper.n_trials=2",
           "hydra.sweeper.n_jobs=2", "model.voxel_size=tag(log, interval(0.05, 0.2))", f"hydra.sweep.dir={sweep}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Pareto front" in done.stdout + done.stderr

    saved = json.loads((sweep / "pareto.json").read_text())
    assert saved["objectives"] == ["psnr", "params"] and saved["directions"] == ["maximize", "minimize"]
    trials = saved["trials"]
    assert [t["job"] for t in trials] == [0, 1] and all(t["state"] == "COMPLETE" for t in trials)
    assert trials[0]["params"] == {"model.voxel_size": "0.017", "prune.ratio": "0.001", "prune": "weights_2_8"}
    for t in trials:  # each job returned its eval.json's (psnr, params.total), and ran the trial's settings
        result = json.loads((sweep / str(t["job"]) / "eval.json").read_text())
        assert t["values"] == {"psnr": pytest.approx(result["psnr"]), "params": result["params"]["total"]}
        overrides = (sweep / str(t["job"]) / ".hydra" / "overrides.yaml").read_text()
        assert all(f"{k}={v}" in overrides for k, v in t["params"].items())
    assert 0.05 <= float(trials[1]["params"]["model.voxel_size"]) <= 0.2

    report = subprocess.run([sys.executable, "-m", "cusgs_jax.app.report", str(sweep)], capture_output=True,
                            text=True, timeout=300)
    assert report.returncode == 0, report.stderr[-3000:]
    rows = list(csv.DictReader((sweep / "report" / "report.csv").open()))
    marked = {int(r["job"]) for r in rows if r["pareto"] == "1"}
    assert marked == {trials[n]["job"] for n in saved["front"]}
    assert "Pareto front (" in report.stdout and "★" in report.stdout


@pytest.mark.parametrize("override, message", [
    ("hydra.sweeper.n_trials=0", "hydra.sweeper.n_trials=0 must be a whole number >= 1"),
    ("hydra.sweeper.directions=[up,minimize]", "'up' is not one of"),
    ("prune.ratio=interval(0.5, 2)", "prune.ratio=2.0: is the fraction of alive anchors"),
    ("model.voxel_size=tag(log, interval(0.08, 0.008))", "the interval runs from 0.08 down to 0.008"),
])
def test_bad_search_settings_exit_2_with_one_line(override, message, tmp_path):
    done = subprocess.run([*APP, "-m", "experiment=pareto_search", override, f"hydra.sweep.dir={tmp_path}/x"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and message in done.stderr, done.stderr[-2000:]
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
