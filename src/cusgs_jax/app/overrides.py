"""Checking a ``cusgs-train`` command line before Hydra runs it.

Hydra reports a bad override with its own message and exit code 1, and a
lexer error gives no hint. :func:`check_command_line` composes the
configuration the command would run — every value of a swept option in turn —
through the same schema (:mod:`cusgs_jax.config`) and returns one message
naming the option and the fix, or None. The caller prints it and exits 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pathlib

from cusgs_jax.compose import compose_config, compose_node
from cusgs_jax.errors import UserError
from cusgs_jax.sweep.pareto import check_sweeper_settings

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
        _check_sweeper([o.input_line for o in overrides if not o.is_sweep_override()],
                       [o.input_line for o in overrides])
        if not args.multirun and not any(o.is_sweep_override() for o in overrides):
            _check_writable(_run_dir(overrides))
    except UserError as error:
        return str(error)
    return None


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


#: The Hydra plugin each optional launcher / sweeper needs, and the extra that installs it.
_EXTRAS = {"hydra/launcher/ray": "ray", "hydra/launcher/submitit": "slurm"}


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


def _check_sweeper(fixed: list[str], arguments: list[str] = ()) -> None:
    """``hydra/sweeper=pareto``: its settings, its search space (``params`` and the sweeps of the command
    line ``arguments``) and every end / choice of ``params`` must compose."""
    from omegaconf import OmegaConf

    sweeper = compose_node(fixed, return_hydra_config=True).hydra.sweeper
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
    from hydra.errors import ConfigCompositionException, MissingConfigException

    try:
        compose_config(overrides)
    except MissingConfigException as error:
        first = str(error).split("\n\n")[0]
        options = _listed_options(str(error))
        extra = next((name for key, name in _EXTRAS.items() if f"'{key}" in first), None)
        hint = f"; the plugin comes with the {extra} extra: pip install -e \".[{extra}]\"" if extra else ""
        raise UserError((f"{first}; choose one of {options}" if options else first) + hint) from None
    except ConfigCompositionException as error:
        raise UserError(_composition_message(error)) from None


def _listed_options(message: str) -> list[str]:
    """The tab-indented names under Hydra's "Available options in 'group':" line."""
    lines = message.split("Available options", 1)[-1].splitlines()[1:] if "Available options" in message else []
    options = []
    for line in lines:
        if not line.startswith("\t"):
            break
        options.append(line.strip())
    return options


def _composition_message(error: Exception) -> str:
    """One line from Hydra's composition error and its OmegaConf cause, with the fix."""
    cause = error.__cause__
    head = str(error).splitlines()[0]
    if cause is None:
        return head
    detail = str(cause).splitlines()[0]
    full_key = next((line.split(":", 1)[1].strip() for line in str(cause).splitlines()
                     if line.strip().startswith("full_key:")), "")
    if type(cause).__name__ in ("ConfigAttributeError", "ConfigKeyError"):
        return f"unknown option {full_key or head}: {detail}; `cusgs-train --cfg job` lists every option"
    return f"{head}: {detail}" + (f" (option {full_key})" if full_key else "")


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
