"""sweep/pareto.py: the search space from Hydra's sweep grammar, the objectives a job returns, and the
ask / launch / tell loop against a fake launcher (failed jobs, the front against brute force, pareto.json)."""

from __future__ import annotations

import json
import math

import pytest

optuna = pytest.importorskip("optuna")  # the optuna extra

from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution  # noqa: E402

from cusgs_jax.sweep.pareto import (  # noqa: E402
    ParetoSearch,
    check_sweeper_settings,
    distributions_from_overrides,
    objective_values,
    result_objectives,
)


def test_search_space_from_hydra_sweep_grammar():
    space, fixed = distributions_from_overrides([
        "model.voxel_size=tag(log, interval(0.008, 0.08))", "prune.ratio=interval(0, 0.05)",
        "model.n_offsets=range(4, 12, 2)", "eval.every=range(0.5, 2.0, 0.5)", "prune=choice(weights_2_8, weights_8_2)",
        "grow.levels=2,3", "train.iterations=600", "experiment=pareto_search", "prune.ratio=0.01"])
    assert space == {
        "model.voxel_size": FloatDistribution(0.008, 0.08, log=True),
        "model.n_offsets": IntDistribution(4, 10, step=2),
        "eval.every": FloatDistribution(0.5, 1.5, step=0.5),
        "prune": CategoricalDistribution(["weights_2_8", "weights_8_2"]),
        "grow.levels": CategoricalDistribution([2, 3]),
    }
    # a later fixed value replaces an earlier search dimension (the command line after the config)
    assert fixed == {"train.iterations": "train.iterations=600", "experiment": "experiment=pareto_search",
                     "prune.ratio": "prune.ratio=0.01"}


def test_objective_values():
    assert objective_values((25.0, 1000), 2) == [25.0, 1000.0]
    assert objective_values([25.0, 1000], 2) == [25.0, 1000.0]
    assert objective_values(25.0, 1) == [25.0]
    for bad in (math.nan, None, "x", (25.0,), (25.0, math.nan), (25.0, math.inf), (1, 2, 3), 25.0):
        assert objective_values(bad, 2) is None
    assert result_objectives({"psnr": 25.5, "params": {"total": 1234, "mlp": 4}}, ["psnr", "params"]) == (25.5, 1234.0)
    assert math.isnan(result_objectives({}, ["ssim"])[0])


def test_check_sweeper_settings():
    good = dict(n_trials=8, n_jobs=2, objectives=["psnr", "params"], directions=["maximize", "minimize"],
                params={"prune.ratio": "interval(0, 0.05)"})
    assert check_sweeper_settings(good) is None
    assert "n_trials" in check_sweeper_settings({**good, "n_trials": 0})
    assert "n_jobs" in check_sweeper_settings({**good, "n_jobs": "2"})
    assert "one direction per objective" in check_sweeper_settings({**good, "directions": ["maximize"]})
    assert "'up'" in check_sweeper_settings({**good, "directions": ["up", "minimize"]})
    assert "hydra.sweeper.params" in check_sweeper_settings({**good, "params": {"prune.ratio": "interval(0"}})


@pytest.mark.parametrize("params, arguments, expected", [
    ({}, ["model.voxel_size=tag(log, interval(0.08, 0.008))"],
     "model.voxel_size=tag(log, interval(0.08, 0.008)): the interval runs from 0.08 down to 0.008; write "
     "model.voxel_size=tag(log, interval(0.008, 0.08))"),
    ({"prune.ratio": "interval(0.05, 0)"}, [],
     "prune.ratio=interval(0.05, 0): the interval runs from 0.05 down to 0.0; write prune.ratio=interval(0.0, 0.05)"),
    ({}, ["model.voxel_size=tag(log, interval(0, 0.08))"], "a log interval needs a low end > 0"),
    ({}, ["model.n_offsets=range(12, 4, 2)"], "range(12, 4, 2) holds no value"),
    ({"model": {"voxel_size": "tag(log, interval(0.008, 0.08))"}}, [],
     "hydra.sweeper.params.model holds a group of options, not one search dimension"),
])
def test_a_search_space_optuna_would_refuse_is_named_before_any_trial(params, arguments, expected):
    good = {"n_trials": 4, "n_jobs": 2, "objectives": ["psnr", "params"], "directions": ["maximize", "minimize"]}
    problem = check_sweeper_settings({**good, "params": params}, arguments)
    assert problem is not None and expected in problem and "\n" not in problem
    assert check_sweeper_settings({**good, "params": {"prune.ratio": "interval(0, 0.05)"}},
                                  ["model.voxel_size=tag(log, interval(0.008, 0.08))", "model.n_offsets=range(4, 12, 2)"]
                                  ) is None


class _Return:
    """Stands in for Hydra's JobReturn: ``return_value`` re-raises a job's exception."""

    def __init__(self, value=None, error=None):
        self._value, self._error = value, error

    @property
    def return_value(self):
        if self._error is not None:
            raise self._error
        return self._value


def _fake_job(overrides):
    """A made-up trade-off: a smaller voxel is sharper and bigger; voxel 0.05 'diverges', 0.06 raises."""
    params = dict(o.split("=", 1) for o in overrides)
    voxel = float(params["model.voxel_size"])
    if 0.049 < voxel < 0.051:
        return _Return(math.nan)
    if 0.059 < voxel < 0.061:
        return _Return(error=RuntimeError("boom"))
    return _Return((30.0 - 100 * voxel + int(params["k"]), 1.0 / voxel + 10 * int(params["k"])))


def test_search_loop_front_and_failed_trials(tmp_path):
    space, fixed = distributions_from_overrides(["model.voxel_size=interval(0.01, 0.1)", "k=choice(0, 1)",
                                                 "train.iterations=5"])
    search = ParetoSearch(["psnr", "params"], ["maximize", "minimize"], n_trials=9, n_jobs=2, space=space,
                          fixed=fixed, sampler=optuna.samplers.TPESampler(seed=1, n_startup_trials=4),
                          enqueue=[{"model.voxel_size": 0.05, "k": 0}, {"model.voxel_size": 0.06, "k": 1}],
                          out_dir=tmp_path)
    batches = []

    def launch(batch, first_job):
        batches.append((first_job, batch))
        return [_fake_job(overrides) for overrides in batch]

    front = search.run(launch, first_job=0)
    assert [len(b) for _, b in batches] == [2, 2, 2, 2, 1] and [j for j, _ in batches] == [0, 2, 4, 6, 8]
    first = batches[0][1]
    assert first[0] == ["model.voxel_size=0.05", "k=0", "train.iterations=5"]
    assert all(o[-1] == "train.iterations=5" for _, b in batches for o in b)
    states = [t.state.name for t in search.study.trials]
    assert states[:2] == ["FAIL", "FAIL"] and states[2:] == ["COMPLETE"] * 7

    # the front is exactly the brute-force non-dominated set of the finished trials
    done = [t for t in search.study.trials if t.state.name == "COMPLETE"]
    brute = {t.number for t in done if not any(
        o.values[0] >= t.values[0] and o.values[1] <= t.values[1] and o.values != t.values for o in done)}
    assert {row["trial"] for row in front} == brute

    saved = json.loads((tmp_path / "pareto.json").read_text())
    assert saved["objectives"] == ["psnr", "params"] and saved["sampler"] == "TPESampler"
    assert len(saved["trials"]) == 9 and set(saved["front"]) == brute
    assert [t["job"] for t in saved["trials"]] == list(range(9))
    assert saved["trials"][0]["values"] is None and saved["trials"][2]["values"]["params"] > 0
    assert saved["fixed"] == ["train.iterations=5"]


def test_mismatched_directions_raise():
    with pytest.raises(ValueError, match="2 objectives"):
        ParetoSearch(["psnr", "params"], ["maximize"], 2, 1, {})
