"""conf/hydra/launcher: the ready sweeps run on Hydra's joblib (default), submitit_local, SLURM
(composition only: no SLURM here) and Ray launchers; a 2-job sweep on each runnable launcher
completes and ``cusgs-report`` reads it. submitit and Ray are the slurm / ray extras."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest
import yaml


APP = [sys.executable, "-m", "cusgs_jax.app.train"]


def _hydra_cfg(*overrides) -> dict:
    done = subprocess.run([*APP, *overrides, "--cfg", "hydra"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    return yaml.safe_load(done.stdout)["hydra"]


def test_ready_sweeps_switch_launcher():
    assert _hydra_cfg("experiment=voxel_size")["launcher"]["n_jobs"] == 2  # joblib_pair
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    launcher = _hydra_cfg("experiment=voxel_size", "hydra/launcher=submitit_local")["launcher"]
    assert launcher["_target_"].endswith("LocalLauncher") and "n_jobs" not in launcher


@pytest.mark.parametrize("option", ["slurm", "submitit_slurm"])
def test_slurm_launcher_composes_with_its_documented_overrides(option):
    """SLURM cannot run here: only the composed launcher config is checked."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    launcher = _hydra_cfg("experiment=prune_ratio", f"hydra/launcher={option}", "hydra.launcher.partition=gpu",
                          "hydra.launcher.gpus_per_node=1", "hydra.launcher.timeout_min=120",
                          "hydra.launcher.mem_gb=48")["launcher"]
    assert launcher["_target_"].endswith("SlurmLauncher")
    assert (launcher["partition"], launcher["gpus_per_node"], launcher["timeout_min"], launcher["mem_gb"]) == \
        ("gpu", 1, 120, 48)
    if option == "slurm":
        assert launcher["cpus_per_task"] == 8 and launcher["array_parallelism"] == 16


def test_bad_launcher_settings_exit_2_with_one_line(tmp_path):
    for argv, message in ((["hydra/launcher=nope"], "Could not find 'hydra/launcher/nope'; choose one of"),
                          (["hydra.launcher.partition=gpu"], "unknown option hydra.launcher.partition")):
        done = subprocess.run([*APP, "-m", "experiment=voxel_size", *argv, f"hydra.sweep.dir={tmp_path}/x"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and message in done.stderr, done.stderr[-2000:]
        assert len(done.stderr.strip().splitlines()) == 1


def _two_job_sweep(tiny_sweep, sweep, launcher_overrides):
    scene, tiny = tiny_sweep
    cmd = [*APP, "-m", f"data.path={scene}", *tiny, "model.voxel_size=0.06,0.1", *launcher_overrides,
           f"hydra.sweep.dir={sweep}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    report = subprocess.run([sys.executable, "-m", "cusgs_jax.app.report", str(sweep)], capture_output=True,
                            text=True, timeout=300)
    assert report.returncode == 0, report.stderr[-3000:]
    rows = list(csv.DictReader((sweep / "report" / "report.csv").open()))
    assert [(r["job"], r["model.voxel_size"], r["status"]) for r in rows] == [("0", "0.06", "ok"), ("1", "0.1", "ok")]
    assert all(float(r["psnr"]) > 5 and int(r["params"]) > 0 for r in rows)
    return done


@pytest.mark.slow  # a whole multi-job sweep / example run: .ci/run runs it with -m slow
def test_submitit_local_two_job_sweep(tiny_sweep, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    sweep = tmp_path / "submitit"
    _two_job_sweep(tiny_sweep, sweep, ["hydra/launcher=submitit_local"])
    assert (sweep / ".submitit").is_dir()  # submitit's own job logs


@pytest.mark.slow  # a whole multi-job sweep / example run: .ci/run runs it with -m slow
def test_ray_two_job_sweep(tiny_sweep, tmp_path):
    """Ray started by the sweep itself with 2 CPUs (ray_local.yaml), stopped when the command exits."""
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    done = _two_job_sweep(tiny_sweep, tmp_path / "ray", ["hydra/launcher=ray_local",
                                                          "hydra.launcher.ray.init.num_cpus=2"])
    assert "Started a local Ray instance" in done.stdout + done.stderr
