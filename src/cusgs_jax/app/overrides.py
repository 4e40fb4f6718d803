"""Checking a ``cusgs-train`` command line before Hydra runs it.

Hydra reports a bad override with its own message and exit code 1, and a
lexer error gives no hint. :func:`check_command_line` composes the
configuration the command would run — every value of a swept option in turn —
through the same schema (:mod:`cusgs_jax.config`) and returns one message
naming the option and the fix, or None. The caller prints it and exits 2.
A sweep over a setting that changes nothing in any of its jobs (a schedule that
never runs within ``train.iterations``, :func:`sweep_warnings`) is logged as one
warning before anything runs.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import logging
import os
import pathlib

from cusgs_jax.compose import compose_config, compose_node
from cusgs_jax.schedules import idle_schedules
from cusgs_jax.errors import UserError
from cusgs_jax.sweep.pareto import check_sweeper_settings

log = logging.getLogger("cusgs_jax")
_INFO_FLAGS = ("help", "hydra_help", "cfg", "info", "shell_completion")


def hydra_args_parser() -> argparse.ArgumentParser:
    """The command line ``@hydra.main`` accepts: its flags and the positional overrides.

    Hydra has no public API for its parser (``hydra._internal.utils.get_args_parser``), so this is
    our own argparse with the same flags, destinations and arities as Hydra 1.3's (a test checks
    them against Hydra's). Used only to tell the overrides from the flags before Hydra runs;
    Hydra itself still parses the command line that runs.
    """
    parser = argparse.ArgumentParser(add_help=False, prog="cusgs-train")
    parser.add_argument("--help", "-h", action="store_true")
    parser.add_argument("--hydra-help", action="store_true")
    parser.add_argument("--version", action="version", version="hydra")
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--cfg", "-c", choices=["job", "hydra", "all"])
    parser.add_argument("--resolve", action="store_true")
    parser.add_argument("--package", "-p")
    parser.add_argument("--run", "-r", action="store_true")
    parser.add_argument("--multirun", "-m", action="store_true")
    parser.add_argument("--shell-completion", "-sc", action="store_true")
    parser.add_argument("--config-path", "-cp")
    parser.add_argument("--config-name", "-cn")
    parser.add_argument("--config-dir", "-cd")
    parser.add_argument("--experimental-rerun")
    parser.add_argument("--info", "-i", const="all", nargs="?",
                        choices=["all", "config", "defaults", "defaults-tree", "plugins", "searchpath"])
    return parser


def check_command_line(argv: list[str]) -> str | None:
    """None when ``argv`` (``cusgs-train``'s arguments) composes into valid configurations, else the problem."""
    args = hydra_args_parser().parse_args(argv)  # argparse itself exits 2 on an unknown flag
    if any(getattr(args, flag, None) for flag in _INFO_FLAGS):
        return None
    try:
        overrides = _parse(args.overrides)
        _check_hydra_sweeps(overrides)
        for variant in _variants(overrides):
            _compose(variant)
        fixed = [o.input_line for o in overrides if not o.is_sweep_override()]
        hydra_node = compose_node(fixed, return_hydra_config=True).hydra
        _check_sweeper(fixed, [o.input_line for o in overrides], hydra_node.sweeper)
        if args.multirun or str(hydra_node.mode) == "RunMode.MULTIRUN":
            for line in sweep_warnings(fixed, _sweeps(overrides, hydra_node.sweeper)):
                log.warning("%s", line)
        if not args.multirun and not any(o.is_sweep_override() for o in overrides):
            _check_writable(_run_dir(overrides))
    except UserError as error:
        return str(error)
    return None


def is_multirun(argv: list[str]) -> bool:
    """Whether ``cusgs-train argv`` runs a sweep: ``-m``, or a composed ``hydra.mode`` of MULTIRUN (the ready
    experiments set it). False for a command line that does not compose (:func:`check_command_line` says why)."""
    args = hydra_args_parser().parse_args(argv)
    if args.multirun:
        return True
    if any(getattr(args, flag, None) for flag in _INFO_FLAGS):
        return False
    try:
        fixed = [o.input_line for o in _parse(args.overrides) if not o.is_sweep_override()]
        return str(compose_node(fixed, return_hydra_config=True).hydra.mode) == "RunMode.MULTIRUN"
    except Exception:  # noqa: BLE001 - not composable: check_command_line reports it
        return False


#: Most jobs whose configurations :func:`sweep_warnings` composes one by one (about 0.1 s each); a larger sweep is
#: checked one swept value at a time, the other sweeps at their first value.
MAX_COMPOSED_JOBS = 48


def _sweeps(overrides, sweeper) -> dict[str, list[str]]:
    """{key: its values} of the sweep Hydra's basic sweeper runs: ``hydra.sweeper.params`` (an experiment's), then
    the command line's sweeps (which replace a param of the same key). Empty for other sweepers (Optuna's)."""
    sweeps = {}
    if str(sweeper.get("_target_", "")).endswith("BasicSweeper"):
        params = sweeper.get("params") or {}
        for sweep in _parse([f"{key}={value}" for key, value in params.items()]):
            values = _sweep_values(sweep) if sweep.is_sweep_override() else [sweep.value()]
            sweeps[sweep.get_key_element()] = [str(v) for v in values]
    for sweep in (o for o in overrides if o.is_sweep_override()):
        sweeps[sweep.get_key_element()] = [str(v) for v in _sweep_values(sweep)]
    return sweeps


def _idle_reason(cfg, key: str) -> str | None:
    """Why a setting ``key`` (``prune.ratio``, a group choice ``prune``) changes nothing in a job of ``cfg``: the
    schedule it belongs to never runs (:func:`cusgs_jax.schedules.idle_schedules`), or None."""
    key = key.lstrip("+~")
    group = key.split(".")[0].split("/")[0]
    idle = idle_schedules(cfg)
    if group == "prune":
        if cfg.prune.strategy != "feature_aware" and key not in ("prune", "prune.strategy"):
            return f"prune.strategy={cfg.prune.strategy} runs no feature-aware pruning pass"
        return idle.get("prune")
    if group == "grow" and not key.startswith("grow.early_cull"):
        return idle.get("grow")
    return idle.get(key)


def sweep_warnings(fixed: list[str], sweeps: dict[str, list[str]]) -> list[str]:
    """One line per swept setting that changes nothing in any job of the sweep (``fixed`` overrides, ``sweeps``
    {key: values}): e.g. ``experiment=prune_ratio train.iterations=300`` sweeps ``prune.ratio``, but no pruning
    pass runs before step 300 (``prune.start=500``), so every job trains the same model."""
    keys = [key for key in sweeps if len(sweeps[key]) > 1]
    if not keys:
        return []
    jobs = [dict(zip(sweeps, values)) for values in itertools.product(*sweeps.values())]
    if len(jobs) > MAX_COMPOSED_JOBS:
        first = {key: values[0] for key, values in sweeps.items()}
        jobs = [dict(first, **{key: value}) for key in keys for value in sweeps[key]]
    reasons: dict[str, list[str | None]] = {key: [] for key in keys}
    for job in jobs:
        cfg = compose_config(fixed + [f"{key}={value}" for key, value in job.items()])
        for key in keys:
            reasons[key].append(_idle_reason(cfg, key))
    return [f"the sweep over {key} ({', '.join(sweeps[key])}) changes nothing in any of its {len(jobs)} jobs: "
            f"{reasons[key][0]}" for key in keys if all(reasons[key])]


def _parse(tokens: list[str]):
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create()
    parsed = []
    for token in tokens:
        try:
            parsed.extend(parser.parse_overrides([token]))
        except OverrideParseException as error:
            reason = str(error).splitlines()[1] if "\n" in str(error) else str(error)
            hint = ("every argument must be key=value; a path with spaces must be quoted as one argument, "
                    "e.g. 'data.path=\"/my scenes/garden\"'") if "=" not in token else \
                "quote values with special characters, e.g. 'data.path=\"/scenes/a,b\"'"
            raise UserError(f"cannot read the override {token!r} ({reason}): {hint}") from None
    return parsed


def _variants(overrides) -> list[list[str]]:
    """Override lists to compose: the fixed overrides plus each value of each swept option in turn."""
    fixed = [o.input_line for o in overrides if not o.is_sweep_override()]
    variants = [fixed]
    for sweep in (o for o in overrides if o.is_sweep_override()):
        for value in _sweep_values(sweep):
            variants.append(fixed + [f"{sweep.get_key_element()}={value}"])
    return variants


def _sweep_values(sweep) -> list:
    """Every value of a choice / range sweep; the two ends of an ``interval`` (Optuna searches between)."""
    from hydra.core.override_parser.types import IntervalSweep

    value = sweep.value()
    if isinstance(value, IntervalSweep):
        return [value.start, value.end]
    return list(sweep.sweep_string_iterator())


def _check_hydra_sweeps(overrides) -> None:
    """Hydra cannot sweep its own ``hydra.*`` settings (it stops with exit 1): say what to write instead."""
    for o in overrides:
        key = o.get_key_element()
        if not (o.is_sweep_override() and key.lstrip("+~").startswith("hydra.")):
            continue
        prefix = "hydra.sweeper.params."
        if key.lstrip("+").startswith(prefix):
            option, value = key.lstrip("+")[len(prefix):], o.input_line.split("=", 1)[1]
            raise UserError(f"{o.input_line!r}: Hydra cannot sweep its own hydra.* settings; give the search "
                            f"dimension as its own override, '{option}={value}' (the "
                            "command line's sweeps join hydra.sweeper.params)")
        raise UserError(f"{o.input_line!r}: Hydra cannot sweep its own hydra.* settings; give {key.lstrip('+')} "
                        "one value")


def _check_sweeper(fixed: list[str], arguments: list[str], sweeper) -> None:
    """``hydra/sweeper=pareto`` (``sweeper``: the composed ``hydra.sweeper``): its settings, its search space
    (``params`` and the sweeps of the command line ``arguments``) and every end / choice of ``params`` must
    compose."""
    from omegaconf import OmegaConf

    if not str(sweeper.get("_target_", "")).endswith("ParetoSweeper"):
        return
    try:
        importlib.import_module("optuna")  # installed and importable
    except ImportError:
        raise UserError("hydra/sweeper=pareto needs Optuna: pip install -e \".[optuna]\"") from None

    problem = check_sweeper_settings(OmegaConf.to_container(sweeper, resolve=False), arguments)
    if problem:
        raise UserError(problem)
    params = sweeper.get("params") or {}
    for sweep in _parse([f"{key}={value}" for key, value in params.items()]):
        for value in _sweep_values(sweep) if sweep.is_sweep_override() else [sweep.value()]:
            _compose(fixed + [f"{sweep.get_key_element()}={value}"])


def _compose(overrides: list[str]) -> None:
    compose_config(overrides)  # a ConfigError in one line (compose.composition_error)


def _run_dir(overrides) -> pathlib.Path:
    for o in overrides:
        if o.get_key_element() == "hydra.run.dir":
            return pathlib.Path(str(o.value()))
    return pathlib.Path("outputs")


def _check_writable(folder: pathlib.Path) -> None:
    """The nearest existing ancestor of ``folder`` must be a folder we can create files in."""
    probe = folder.absolute()
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise UserError(f"hydra.run.dir={folder}: {probe} is a file, so the output folder cannot be created; "
                        "set hydra.run.dir=<a writable folder>")
    try:
        fd = os.open(probe / f".cusgs-write-test-{os.getpid()}", os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        os.close(fd)
        os.unlink(probe / f".cusgs-write-test-{os.getpid()}")
    except OSError as error:
        raise UserError(f"hydra.run.dir={folder}: cannot write into {probe} ({error.strerror}); run from a writable "
                        "folder or set hydra.run.dir=<a writable folder>") from None
