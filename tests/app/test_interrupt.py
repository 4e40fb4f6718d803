"""Interruptions of a real cusgs-train run (app/interrupt.py), driven by signals sent to its process: Ctrl-C exits
within seconds with one line (once or twice, never an abort), SIGTERM checkpoints the step it reached and the run
resumes from it."""

from __future__ import annotations

import json
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from cusgs_jax.app.interrupt import INTERRUPT_GRACE_S, TERMINATE_GRACE_S, handling, requested

RUN = ["train.iterations=5000", "train.progress=false", "eval.every=0", "train.log_every=5", "model.n_offsets=4",
       "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8", "features=none"]


def _start(scene, out: pathlib.Path, *extra: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "cusgs_jax.app.train", f"data.path={scene}", f"hydra.run.dir={out}",
               f"train.compilation_cache={out.parent / 'xla_cache'}", *RUN, *extra]
    out.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=open(out / "stderr.txt", "w"))


def _stopped(process: subprocess.Popen, signum: int, out: pathlib.Path, times: int = 1) -> tuple[int, float, str]:
    """Send ``signum`` (``times`` times, 0.2 s apart); (exit code, seconds from the first signal to the exit, stderr)."""
    start = time.perf_counter()
    for _ in range(times):
        process.send_signal(signum)
        time.sleep(0.2)
    code = process.wait(timeout=60)
    return code, time.perf_counter() - start, (out / "stderr.txt").read_text()


def _stepping(out: pathlib.Path, steps: int, timeout: float = 240) -> None:
    """Wait until the run has logged ``steps`` steps (metrics.jsonl)."""
    deadline = time.monotonic() + timeout
    metrics = out / "metrics.jsonl"
    while time.monotonic() < deadline:
        if metrics.is_file() and any(json.loads(line)["step"] >= steps
                                     for line in metrics.read_text().splitlines() if line.strip()):
            return
        time.sleep(0.2)
    raise AssertionError(f"the run did not reach step {steps}")


def test_a_signal_only_sets_a_flag_and_the_handlers_go_back():
    before = signal.getsignal(signal.SIGTERM)
    with handling("t"):
        assert requested() is None
        signal.raise_signal(signal.SIGTERM)  # no exception: the loop looks at the flag between steps
        assert requested() == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before and requested() is None


@pytest.mark.parametrize("times", [1, 2])
def test_ctrl_c_during_the_start_exits_within_seconds_with_one_line(tmp_path, tiny_scene, times):
    """Ctrl-C 2 s in (imports, scene loading, the first compiles): exit 130 within the grace period plus a margin,
    one line on stderr, no traceback; a second Ctrl-C changes nothing (no C++ abort, exit 134)."""
    out = tmp_path / "run"
    process = _start(tiny_scene, out)
    time.sleep(2.0)
    code, seconds, stderr = _stopped(process, signal.SIGINT, out, times)
    assert code == 130, stderr
    assert seconds < INTERRUPT_GRACE_S + 1.5, seconds
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("[")]  # not log lines
    assert lines == [lines[-1]] and lines[-1].startswith("cusgs-train: interrupted (Ctrl-C)"), stderr
    assert "Traceback" not in stderr and "terminate called" not in stderr


@pytest.mark.slow  # two runs of a few hundred steps (about a minute on 2 cores)
def test_sigterm_checkpoints_the_step_it_reached_and_the_run_resumes_from_it(tmp_path, tiny_scene):
    out = tmp_path / "run"
    process = _start(tiny_scene, out, "train.checkpoint_every=1000")
    _stepping(out, 20)
    code, seconds, stderr = _stopped(process, signal.SIGTERM, out)
    assert code == 143 and seconds < TERMINATE_GRACE_S + 2, (code, seconds, stderr)  # a compile may finish first
    assert "Traceback" not in stderr and "@ " not in stderr  # no C++ stack dump (glog's failure-signal handler)
    line = [line for line in stderr.splitlines() if line.startswith("cusgs-train:")]
    assert len(line) == 1 and "terminated (SIGTERM) after step" in line[0], stderr
    step = int(line[0].split("after step ")[1].split(";")[0])
    assert step >= 20 and sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == [step]
    resumed = subprocess.run([sys.executable, "-m", "cusgs_jax.app.train", f"data.path={tiny_scene}",
                              f"hydra.run.dir={out}", f"train.compilation_cache={tmp_path / 'xla_cache'}",
                              *[o for o in RUN if not o.startswith("train.iterations")],
                              f"train.iterations={step + 10}", "train.checkpoint_every=1000", "train.resume=true"],
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert f"resumed from step {step}" in resumed.stdout + resumed.stderr  # Hydra logs to stdout
    assert json.loads((out / "eval.json").read_text())["iterations"] == step + 10
