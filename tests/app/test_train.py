"""The Hydra app (app/train.py, ``cusgs-train`` / ``python -m cusgs_jax.app.train``): single runs, bad
paths, the ready sweeps, and a joblib sweep that survives a failing job and is read by cusgs-report."""

from __future__ import annotations

import csv
import json
import pathlib
import shutil
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from cusgs_jax.app.train import record_failure
from cusgs_jax.config import Config
from cusgs_jax.compose import compose_config, register_configs
from cusgs_jax.data.demo import generate_demo_scene

APP = [sys.executable, "-m", "cusgs_jax.app.train"]

TINY = ["train.iterations=6", "train.checkpoint_every=0", "train.progress=false", "eval.every=6",
        "grow.stats_start=1", "grow.start=4", "grow.stop=6", "grow.interval=2",
        "prune.start=2", "prune.interval=2", "prune.ratio=0.05", "eval.save_renders=false",
        "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8",
        "model.voxel_size=0.06"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return generate_demo_scene(tmp_path_factory.mktemp("scene") / "demo", num_views=9, width=32, height=24,
                               num_points=800)


def _console_script(name):
    """The installed console script next to this interpreter (else on PATH)."""
    path = pathlib.Path(sys.executable).parent / name
    return str(path) if path.is_file() else shutil.which(name)


def test_no_overrides_compose_the_dataclass_defaults():
    """``cusgs-train`` with no overrides runs exactly ``Config()`` (config.py holds every default)."""
    assert compose_config([]) == Config()
    cfg = compose_config(["model.voxel_size=0.1", "train.iterations=50"])
    assert cfg == Config().replace(model=dict(voxel_size=0.1), train=dict(iterations=50))


@pytest.mark.parametrize("name", ["voxel_size", "prune_ratio", "prune_strategy", "prune_weights", "queries"])
def test_every_ready_sweep_composes(name):
    register_configs()
    with initialize_config_module("cusgs_jax.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"experiment={name}"], return_hydra_config=True)
    params = cfg.hydra.sweeper.params
    assert len(params) == 1 and len(str(next(iter(params.values()))).split(",")) >= 2
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher")
    assert cfg.train.iterations < 3000  # reduced schedule for the 2-core demo sweeps
    assert OmegaConf.select(cfg, "hydra.sweep.dir").startswith(f"multirun/{name}/")


def test_weight_options_set_the_pairs():
    for n, g in ((8, 2), (6, 4), (4, 6), (2, 8)):
        cfg = compose_config([f"prune=weights_{n}_{g}"])
        assert (cfg.prune.lambda_norm, cfg.prune.lambda_grad, cfg.prune.strategy) == (n, g, "feature_aware")


def test_record_failure_writes_error_and_traceback(tmp_path):
    try:
        raise ValueError("bad voxel size")
    except ValueError as error:
        path = record_failure(tmp_path / "job", error)
    data = json.loads(path.read_text())
    assert data["error"] == "ValueError: bad voxel size" and "Traceback" in data["traceback"]


@pytest.mark.slow  # 29 s on 2 cores: kept out of the default run; .ci/run's -m slow pass runs it
def test_hydra_app_runs_and_reports_bad_paths(tiny_scene, tmp_path):
    cmd = [*APP, f"data.path={tiny_scene}", *TINY, f"hydra.run.dir={tmp_path / 'app'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "app" / "eval.json").is_file()
    assert json.loads((tmp_path / "app" / "eval.json").read_text())["iterations"] == 6
    # the console script, on a scene that does not exist: exit status 2 and the path in the message
    script = _console_script("cusgs-train")
    assert script, "the cusgs-train console script is not installed"
    missing = tmp_path / "no_such_scene"
    cmd = [script, f"data.path={missing}", f"hydra.run.dir={tmp_path / 'bad'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 2
    assert str(missing) in done.stderr + done.stdout
    assert str(missing) in json.loads((tmp_path / "bad" / "failed.json").read_text())["error"]


@pytest.mark.parametrize("override", ["model.no_such_option=1", "+model.foo=1", "train.iterations=abc",
                                      "prune.ratio=1.0", "model.voxel_size=0"])
def test_bad_settings_exit_2_with_one_line_before_any_work(tmp_path, override):
    done = subprocess.run([*APP, override, f"hydra.run.dir={tmp_path / 'x'}"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and override.split("=")[0].lstrip("+") in done.stderr
    assert done.stderr.startswith("cusgs-train: error: ") and len(done.stderr.strip().splitlines()) == 1
    assert "Traceback" not in done.stderr and not (tmp_path / "x").exists()


@pytest.mark.slow  # a whole multi-job sweep / example run: .ci/run runs it with -m slow
def test_sweep_survives_a_failing_job_and_reports_it(tiny_scene, tmp_path):
    missing = tmp_path / "no_such_scene"
    sweep = tmp_path / "sweep"
    cmd = [*APP, "-m", f"data.path={tiny_scene},{missing}", *TINY,
           "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    # the good job finished; the sweep still fails (2: the failed job was a bad setting/input), naming the job
    assert done.returncode == 2, done.stderr[-3000:]
    assert "1 sweep job(s) failed" in done.stderr and str(sweep / "1" / "failed.json") in done.stderr
    good, bad = sweep / "0", sweep / "1"
    result = json.loads((good / "eval.json").read_text())
    assert result["prune"]["passes"] == 3 and result["prune"]["pruned"] > 0
    # two jobs side by side share the accelerator: each took 0.9 / 2 of its memory (app/accelerator.py)
    assert result["accelerator"]["memory_fraction"] == "0.450"
    assert (good / ".hydra" / "overrides.yaml").is_file()
    assert str(missing) in json.loads((bad / "failed.json").read_text())["error"]
    assert not (bad / "eval.json").exists()

    report = subprocess.run([sys.executable, "-m", "cusgs_jax.app.report", str(sweep)], capture_output=True,
                            text=True, timeout=300)
    assert report.returncode == 0, report.stderr[-3000:]
    rows = list(csv.DictReader((sweep / "report" / "report.csv").open()))
    assert [r["status"].split(":")[0] for r in rows] == ["ok", "failed"]
    assert float(rows[0]["psnr"]) == pytest.approx(result["psnr"])
    assert (sweep / "report" / "psnr_vs_time.png").is_file()


BROKEN_POOL = """
import pathlib, sys
from hydra._internal.core_plugins.basic_launcher import BasicLauncher
from hydra.core.plugins import Plugins
from joblib.externals.loky.process_executor import TerminatedWorkerError
from cusgs_jax.app.train import main

sweep = pathlib.Path(sys.argv[1])

def launch(self, job_overrides, initial_job_idx):  # joblib's pool when a worker is killed: jobs started, then lost
    for job in ("0", "1"):
        (sweep / job / ".hydra").mkdir(parents=True)
        (sweep / job / ".hydra" / "config.yaml").write_text("train: {}")
    (sweep / "1" / "eval.json").write_text("{}")  # finished before the pool broke: not lost
    raise TerminatedWorkerError("A worker process managed by the executor was unexpectedly terminated. This could be "
                                "caused by a segmentation fault while calling the function or by an excessive memory "
                                "usage causing the Operating System to kill the worker.")

Plugins.instance()  # Hydra's plugin scan loads the launcher modules afresh: patch the class it will use
sys.modules[BasicLauncher.__module__].BasicLauncher.launch = launch
main(["-m", "train.seed=0,1", f"data.path={sweep / 'no_scene'}", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"])
"""


def test_a_broken_launcher_pool_is_reported_in_the_clis_own_lines_only(tmp_path):
    """A sweep whose launcher's worker pool breaks (joblib's, when a worker is killed) names each lost job and the
    launcher's error in cusgs-train's own lines: no traceback from Hydra."""
    import os

    sweep = tmp_path / "sweep"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "-c", BROKEN_POOL, str(sweep)], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path, env=env)
    assert done.returncode == 1, done.stderr[-3000:]
    assert "Traceback" not in done.stderr and "HYDRA_FULL_ERROR" not in done.stderr, done.stderr
    assert done.stderr.splitlines() == [
        f"cusgs-train: job lost: {sweep / '0'} did not finish; rerun the sweep with train.resume=true to continue it",
        "cusgs-train: error: the sweep's launcher stopped (TerminatedWorkerError: a job's process ended abruptly, "
        "killed or out of memory); 1 job(s) lost, their checkpoints kept"]
    assert json.loads((sweep / "0" / "failed.json").read_text())["error"].startswith("JobLost:")
    assert not (sweep / "1" / "failed.json").exists()


@pytest.mark.slow  # a 2-job sweep whose worker is killed: .ci/run runs it with -m slow
def test_a_sweep_whose_worker_is_killed_records_every_lost_job(tiny_scene, tmp_path):
    """kill -9 of one joblib worker breaks the pool, which stops the other job too: the command exits non-zero and
    each started job without eval.json gets a failed.json saying it was lost and how to continue (cusgs-report then
    lists them as failed, not as running)."""
    import signal
    import time

    import psutil

    sweep = tmp_path / "sweep"
    long = [*TINY, "train.iterations=5000", "eval.every=0", "grow.stop=5000"]
    cmd = [*APP, "-m", f"data.path={tiny_scene}", "train.seed=0,1", *long, "hydra/launcher=joblib",
           "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}"]
    sweep_process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not all((sweep / str(job) / "metrics.jsonl").is_file() for job in (0, 1)):  # both jobs training
            assert time.monotonic() < deadline and sweep_process.poll() is None, sweep_process.stderr.read()[-3000:]
            time.sleep(0.5)
        workers = [child for child in psutil.Process(sweep_process.pid).children(recursive=True)
                   if "popen_loky" in " ".join(child.cmdline())]  # not the resource tracker
        assert len(workers) >= 2, [w.cmdline() for w in workers]
        workers[0].send_signal(signal.SIGKILL)
        _, stderr = sweep_process.communicate(timeout=300)
    finally:
        if sweep_process.poll() is None:
            sweep_process.kill()
    assert sweep_process.returncode not in (0, None)
    for job in (0, 1):
        failure = json.loads((sweep / str(job) / "failed.json").read_text())
        assert failure["error"].startswith("JobLost:") and "train.resume=true" in failure["error"]
        assert f"job lost: {sweep / str(job)} did not finish" in stderr
    assert "Traceback" not in stderr and "the sweep's launcher stopped (TerminatedWorkerError" in stderr, stderr
    assert not (sweep / "0" / "eval.json").exists()
    report = subprocess.run([sys.executable, "-m", "cusgs_jax.app.report", str(sweep)], capture_output=True,
                            text=True, timeout=300)
    rows = list(csv.DictReader((sweep / "report" / "report.csv").open()))
    assert [r["status"].split(":")[:2] for r in rows] == [["failed", " JobLost"]] * 2, report.stderr[-2000:]
