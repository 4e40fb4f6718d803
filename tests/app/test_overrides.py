"""Command-line checks before Hydra runs (app/overrides.py): one line naming the option and the fix."""

from __future__ import annotations

import pytest

from cusgs_jax.app.overrides import check_command_line


@pytest.mark.parametrize("argv, expected", [
    (["model.voxel_size=0"], r"model\.voxel_size=0: must be 'auto' or a cell size > 0.*model\.voxel_size=auto"),
    (["model.voxel_size=-1"], r"model\.voxel_size=-1"),
    (["train.iterations=abc"], r"train\.iterations=abc.*could not be converted to Integer.*option train\.iterations"),
    (["train.iterations=-5"], r"train\.iterations=-5: must be a whole number of steps >= 1"),
    (["+model.foo=1"], r"^model\.foo=1: no such option; model holds voxel_size, n_offsets"),
    (["model.foo=1"], r"^model\.foo=1: no such option; model holds voxel_size, n_offsets"),
    (["train.iteration=5"], r"^train\.iteration=5: no such option; did you mean train\.iterations\? \(train holds"),
    (["trian.iterations=5"], r"^trian\.iterations=5: no such option; did you mean train\.iterations\?"),
    (["optim.offsets=[0.01]"], r"^optim\.offsets=\[0\.01\]: must be two finite learning rates >= 0"),
    (["-m", "optim.offsets=[0.01,0.001],[nan,1]"], r"^optim\.offsets=\[nan, 1\.0\]: must be two finite"),
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
    assert problem is not None and "\n" not in problem and "To append" not in problem
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


@pytest.mark.parametrize("argv, swept", [
    (["-m", "experiment=prune_ratio", "train.iterations=300"], "prune.ratio (0.0, 0.001, 0.01, 0.05)"),
    (["experiment=prune_weights", "train.iterations=300"],
     "prune (weights_8_2, weights_6_4, weights_4_6, weights_2_8)"),
    (["-m", "prune.lambda_norm=2,4", "train.iterations=300", "train.seed=0,1"], "prune.lambda_norm (2, 4)"),
    (["-m", "prune.ratio=0.1,0.2", "prune.strategy=none"], "prune.ratio (0.1, 0.2)"),
])
def test_a_sweep_that_changes_nothing_is_warned_about_once_before_it_runs(argv, swept, tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        assert check_command_line(argv) is None
    lines = [r.getMessage() for r in caplog.records if r.name == "cusgs_jax" and r.levelname == "WARNING"]
    assert len(lines) == 1 and lines[0].startswith(f"the sweep over {swept} changes nothing in any of its"), lines
    assert ("prune.start=500 is past train.iterations=300: no pruning pass runs; e.g. prune.start=100" in lines[0]
            or "prune.strategy=none runs no feature-aware pruning pass" in lines[0])


def test_a_sweep_whose_settings_take_effect_is_not_warned_about(tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    with caplog.at_level("WARNING", logger="cusgs_jax"):
        assert check_command_line(["-m", "experiment=prune_ratio"]) is None  # 1500 steps: passes from step 500
        assert check_command_line(["-m", "prune.ratio=0.1,0.2", "train.iterations=300", "prune.start=100"]) is None
        assert check_command_line(["train.iterations=300"]) is None  # a single run: its own setup warns
    assert not [r for r in caplog.records if r.name == "cusgs_jax"]
