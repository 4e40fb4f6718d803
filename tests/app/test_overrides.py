"""Command-line checks before Hydra runs (app/overrides.py): one line naming the option and the fix."""

from __future__ import annotations

import pytest

from cusgs_jax.app.overrides import check_command_line


@pytest.mark.parametrize("argv, expected", [
    (["model.voxel_size=0"], r"model\.voxel_size=0: must be 'auto' or a cell size > 0.*model\.voxel_size=auto"),
    (["model.voxel_size=-1"], r"model\.voxel_size=-1"),
    (["train.iterations=abc"], r"train\.iterations=abc.*could not be converted to Integer.*option train\.iterations"),
    (["train.iterations=-5"], r"train\.iterations=-5: must be a whole number of steps >= 1"),
    (["+model.foo=1"], r"unknown option\(s\) \['model\.foo'\]; valid: \['model\.voxel_size'"),
    (["model.foo=1"], r"unknown option model\.foo.*cusgs-train --cfg job"),
    (["prune.ratio=1.5"], r"prune\.ratio=1\.5: .*must lie in \[0, 1\)"),
    (["prune.ratio=1.0"], r"prune\.ratio=1\.0: .*1 would remove every anchor"),
    (["prune.ratio=-0.1"], r"prune\.ratio=-0\.1"),
    (["model.n_offsets=0"], r"model\.n_offsets=0: must be a number >= 1"),
    (["experiment=nope"], r"Could not find 'experiment/nope'; choose one of \['pareto_search', 'prune_ratio'"),
    (["data.path=/my", "scenes/garden"], r"'scenes/garden'.*a path with spaces must be quoted.*data\.path="),
    (["-m", "model.voxel_size=0.01,0"], r"model\.voxel_size=0: "),  # every swept value is checked
    (["-m", "hydra/sweeper=pareto", "model.voxel_size=tag(log, interval(0.08, 0.008))"],
     r"model\.voxel_size=tag\(log, interval\(0\.08, 0\.008\)\): the interval runs from 0\.08 down to 0\.008; "
     r"write model\.voxel_size=tag\(log, interval\(0\.008, 0\.08\)\)"),
    (["-m", "hydra/sweeper=pareto", "+hydra.sweeper.params.model.voxel_size=tag(log, interval(0.008, 0.08))"],
     r"Hydra cannot sweep its own hydra\.\* settings; .*'model\.voxel_size=tag\(log, interval\(0\.008, 0\.08\)\)'"),
    (["-m", "hydra.sweeper.n_trials=1,2"], r"give hydra\.sweeper\.n_trials one value"),
])
def test_bad_command_lines_are_named_with_the_fix(argv, expected, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    problem = check_command_line(argv)
    assert problem is not None and "\n" not in problem
    import re

    assert re.search(expected, problem), problem


def test_good_command_lines_pass(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert check_command_line([]) is None
    assert check_command_line(["model.voxel_size=0.01", "prune.ratio=0.01", 'data.path="/my scenes/x"']) is None
    assert check_command_line(["-m", "experiment=voxel_size"]) is None
    assert check_command_line(["--cfg", "job"]) is None
    assert not any(tmp_path.iterdir())  # checking writes nothing


def test_an_output_folder_that_cannot_be_created_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("x")
    problem = check_command_line([f"hydra.run.dir={tmp_path / 'a_file' / 'run'}"])
    assert problem is not None and "a_file is a file" in problem and "hydra.run.dir=" in problem
    assert check_command_line([f"hydra.run.dir={tmp_path / 'new' / 'run'}"]) is None


def test_our_parser_has_hydras_flags():
    """hydra_args_parser mirrors Hydra's private get_args_parser (the oracle here, never in the library):
    the same option strings, destinations, arities, constants and choices."""
    from hydra._internal.utils import get_args_parser

    from cusgs_jax.app.overrides import hydra_args_parser

    def signature(parser):
        return sorted((tuple(a.option_strings), a.dest, a.nargs, a.const, tuple(a.choices or ()))
                      for a in parser._actions)

    assert signature(hydra_args_parser()) == signature(get_args_parser())
    for argv in (["-m", "a=1", "b=2"], ["--cfg", "job", "x=1"], ["-i"], ["--info", "config"], ["-cn", "c", "y=2"]):
        assert vars(hydra_args_parser().parse_args(argv)) == vars(get_args_parser().parse_args(argv)), argv
