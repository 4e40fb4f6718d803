"""``cusgs-train``: the Hydra entry point (a thin shell around :func:`cusgs_jax.app.run.run`).

Single runs: ``cusgs-train model.voxel_size=0.02``. Sweeps:
``cusgs-train -m experiment=voxel_size`` (the ready sweeps are in ``conf/experiment``;
they run side by side with Hydra's joblib launcher; ``hydra/launcher=submitit_local``, ``slurm``
or ``ray_local`` run them elsewhere). ``cusgs-train -m experiment=pareto_search`` is a
multi-objective Optuna search (:mod:`cusgs_jax.sweep.pareto`): each job then returns
``(PSNR, parameter count)``, the objectives ``hydra.sweeper.objectives`` names.

Exit codes: 0 success; 2 a bad setting or bad input (one line on stderr naming
the option or file and the fix — checked before any work where possible,
:mod:`cusgs_jax.app.overrides`); 1 a bug (traceback). In a sweep a job that
raises writes ``failed.json`` (error and traceback) into its own folder, is
logged, and the other jobs go on; when the sweep ends, :class:`FailedJobs`
lists the failed jobs and the command exits 2 (all of them bad settings or
input) or 1, never 0. ``cusgs-report <multirun folder>`` lists them too.
"""

from __future__ import annotations

import time

_STARTED = [time.perf_counter()]  # this process's start, near enough: its first run's time budget begins here

import json
import logging
import math
import os
import pathlib
import sys
import traceback

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

from cusgs_jax.app import interrupt
from cusgs_jax.app.accelerator import sweep_memory_env
from cusgs_jax.app.overrides import check_command_line
from cusgs_jax.compose import from_omegaconf, register_configs
from cusgs_jax.errors import UserError
from cusgs_jax.run_folder import EVAL_FILE, FAILED_FILE, HYDRA_DIR
from cusgs_jax.sweep.pareto import result_objectives

log = logging.getLogger("cusgs_jax")
register_configs()  # config.Config is the schema and the defaults of conf/config.yaml
PROG = "cusgs-train"


def record_failure(output_dir: str | pathlib.Path, error: BaseException) -> pathlib.Path:
    """Write ``failed.json`` ({"error": "Type: message", "user_error": bool, "traceback": ...}) into a job folder."""
    path = pathlib.Path(output_dir) / FAILED_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "error": f"{type(error).__name__}: {error}",
        "user_error": isinstance(error, UserError),
        "traceback": "".join(traceback.format_exception(type(error), error, error.__traceback__)),
    }, indent=1))
    return path


class FailedJobs(Callback):
    """Hydra callback: the sweep's folder when it starts, and after it the jobs that wrote ``failed.json`` (read by
    :func:`main`)."""

    found: list[dict] = []
    sweep_dir: pathlib.Path | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        FailedJobs.sweep_dir = pathlib.Path(str(config.hydra.sweep.dir))

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = pathlib.Path(str(config.hydra.sweep.dir))
        FailedJobs.found = [dict(json.loads(path.read_text()), path=str(path))
                            for path in sorted(sweep_dir.glob(f"*/{FAILED_FILE}"))]


LOST = ("JobLost: the job's process ended before the job did (killed, or stopped with the launcher's worker pool "
        "when another job's process died); its checkpoints are kept: rerun the sweep with train.resume=true to "
        "continue it")


def record_lost_jobs(sweep_dir: pathlib.Path) -> list[pathlib.Path]:
    """Write ``failed.json`` (:data:`LOST`) into every job folder under ``sweep_dir`` that Hydra started
    (``.hydra/``) and that holds neither ``eval.json`` nor ``failed.json``: a sweep whose launcher broke (a worker
    killed: joblib's pool then stops every other job too) says which jobs it lost. Returns the files written."""
    from cusgs_jax.app.report import find_jobs  # the job-folder search cusgs-report uses (lazy: --help stays light)

    written = []
    for job in find_jobs(sweep_dir):
        if (job / HYDRA_DIR).is_dir() and not (job / EVAL_FILE).exists() and not (job / FAILED_FILE).exists():
            (job / FAILED_FILE).write_text(json.dumps({"error": LOST, "user_error": False, "traceback": ""}, indent=1))
            written.append(job / FAILED_FILE)
    return written


def _parallel_jobs(hydra_cfg) -> int | None:
    """How many jobs the sweep's launcher runs at once on this machine (joblib's ``n_jobs``), or None."""
    launcher = hydra_cfg.launcher
    n_jobs = launcher.get("n_jobs") if isinstance(launcher, DictConfig) else None
    return None if n_jobs is None else int(n_jobs)


def _objectives(hydra_cfg) -> list[str]:
    """The objective names a multi-objective sweeper asks for (``hydra.sweeper.objectives``), else []."""
    names = hydra_cfg.sweeper.get("objectives") if isinstance(hydra_cfg.sweeper, DictConfig) else None
    return [str(name) for name in names] if names else []


@hydra.main(version_base="1.3", config_path="pkg://cusgs_jax.conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> float | tuple[float, ...]:
    """One run; returns held-out PSNR, or the sweeper's ``objectives`` (e.g. PSNR and parameter count)."""
    from cusgs_jax.app.api import train  # lazy: the run imports JAX (keeps --help free of it)

    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax is chatty at INFO
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" at INFO in every job log
    hydra_cfg = HydraConfig.get()
    output_dir = hydra_cfg.runtime.output_dir
    sweeping = hydra_cfg.mode == RunMode.MULTIRUN
    (pathlib.Path(output_dir) / FAILED_FILE).unlink(missing_ok=True)  # a rerun's job: its old failure is history
    started = _STARTED.pop() if _STARTED else None  # only the process's first run charges the start-up to its budget
    if sweeping:  # jobs side by side on one machine share its accelerator (before JAX's backend starts)
        shared = sweep_memory_env(_parallel_jobs(hydra_cfg))
        os.environ.update(shared)
        if shared:
            log.info("job %s: %s", hydra_cfg.job.num, ", ".join(f"{k}={v}" for k, v in shared.items()))
    try:
        result = train(from_omegaconf(cfg), output_dir, log=False,  # Hydra set the logging up
                       progress_label=f"job {hydra_cfg.job.num}" if sweeping else "train", started=started).record
    except interrupt.Interrupted as stopped:  # one line; background compiles are abandoned, not waited for
        print(f"{PROG}: {stopped}", file=sys.stderr, flush=True)
        logging.shutdown()  # the job's log file complete
        os._exit(stopped.exit_code)
    except UserError as error:
        record_failure(output_dir, error)
        if sweeping:
            log.error("job %s: %s", hydra_cfg.job.num, error)
            return math.nan
        log.error("%s", error)
        raise SystemExit(2) from None
    except Exception as error:  # noqa: BLE001 - a sweep must outlive one bad job
        if not sweeping:
            raise
        path = record_failure(output_dir, error)
        log.exception("job %s failed (details in %s); the other jobs go on", hydra_cfg.job.num, path)
        return math.nan
    objectives = _objectives(hydra_cfg)
    if objectives:  # hydra/sweeper=pareto (cusgs_jax/sweep/pareto.py)
        return result_objectives(result, objectives)
    return float(result.psnr)


def main(argv: list[str] | None = None) -> None:
    """``cusgs-train [overrides]``: check the command line, run Hydra, report failed sweep jobs."""
    argv = sys.argv[1:] if argv is None else list(argv)
    problem = check_command_line(argv)
    if problem:
        print(f"{PROG}: error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    sys.argv = [sys.argv[0] or PROG] + argv
    FailedJobs.found, FailedJobs.sweep_dir = [], None
    from concurrent.futures import BrokenExecutor

    from hydra.errors import CompactHydraException

    from cusgs_jax.app.overrides import is_multirun

    # A sweep's launcher error (a killed joblib worker breaks loky's pool: TerminatedWorkerError) would be printed by
    # Hydra as a traceback before it exits 1; with HYDRA_FULL_ERROR set Hydra raises it instead, so the lines below
    # are the only ones said about it. The jobs' own errors never get here (_hydra_main records them). A single run
    # keeps Hydra's reporting.
    sweeping, full_error = is_multirun(argv), os.environ.get("HYDRA_FULL_ERROR")
    if sweeping:
        os.environ["HYDRA_FULL_ERROR"] = "1"

    def report_lost_jobs() -> list[pathlib.Path]:
        lost = record_lost_jobs(FailedJobs.sweep_dir) if FailedJobs.sweep_dir is not None else []
        for path in lost:
            print(f"{PROG}: job lost: {path.parent} did not finish; rerun the sweep with train.resume=true to "
                  "continue it", file=sys.stderr)
        return lost

    try:
        with interrupt.handling(PROG):  # Ctrl-C stops within seconds, SIGTERM checkpoints first (app/interrupt.py)
            _hydra_main()
    except SystemExit as stopped:  # a launcher that exits by itself
        if stopped.code not in (0, None):
            report_lost_jobs()
        raise
    except BrokenExecutor as error:  # the launcher's worker pool broke: a job's process was killed
        if not sweeping or full_error:  # the user asked for Hydra's full error: theirs
            raise
        lost = report_lost_jobs()
        print(f"{PROG}: error: the sweep's launcher stopped ({type(error).__name__}: a job's process ended "
              f"abruptly, killed or out of memory); {len(lost)} job(s) lost, their checkpoints kept", file=sys.stderr)
        raise SystemExit(1) from None
    except CompactHydraException as error:  # Hydra's own one-line errors, as Hydra prints them
        if not sweeping or full_error:
            raise
        report_lost_jobs()
        lines = [(str(e).strip().splitlines() or [type(e).__name__])[0] for e in (error, error.__cause__) if e]
        print(f"{PROG}: error: {': '.join(lines)}", file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        if sweeping and full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
    if FailedJobs.found:
        for job in FailedJobs.found:
            print(f"{PROG}: job failed: {job['error'].splitlines()[0]} ({job['path']})", file=sys.stderr)
        print(f"{PROG}: error: {len(FailedJobs.found)} sweep job(s) failed; the others finished", file=sys.stderr)
        raise SystemExit(2 if all(job.get("user_error") for job in FailedJobs.found) else 1)


if __name__ == "__main__":
    # run the imported module's main, so FailedJobs (which Hydra instantiates from cusgs_jax.app.train) is one class
    from cusgs_jax.app.train import main as _main

    _main()
