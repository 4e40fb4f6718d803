"""The Strategy protocol (densify/base.py): UpdateInfo, Tally, the optional hooks, and a strategy
defined here, outside the package, trained through app/run.py unchanged (``extra_strategies``)."""

from __future__ import annotations

import inspect
import json

import jax.numpy as jnp
import numpy as np
import pytest

from cusgs_jax.app import run as run_module
from cusgs_jax.compose import compose_config
from cusgs_jax.data.demo import generate_demo_scene
from cusgs_jax.densify.base import Probe, Strategy, Tally, UpdateInfo
from cusgs_jax.densify.factory import make_strategies


class CountViews(Strategy):
    """A toy strategy: counts the finite views the step saw, changes no anchor, every 2nd step."""

    name = "count_views"

    def __init__(self):
        self.probed = []  # the steps at which before_first_update was called

    def init_state(self, capacity: int):
        del capacity
        return jnp.zeros((), jnp.int32)  # not a PerAnchor: growing the capacity leaves it alone

    def accumulate(self, stats, view):
        return stats + view.finite.astype(jnp.int32)

    def due(self, step: int) -> bool:
        return step % 2 == 0

    def before_first_update(self, probe: Probe) -> dict:
        self.probed.append(probe.step)
        return dict(first_step=probe.step, render_ms=probe.render_ms_per_view())

    def update(self, state, tx, step: int):
        del tx, step
        return state, UpdateInfo(extra=dict(views=state.densify[self.name]))  # a 0-d array: the tally makes it plain

    def log_values(self, tally: Tally) -> dict:
        return dict(count_views_updates=tally.updates)

    def results(self, tally: Tally) -> dict:
        return dict(counted_views=tally.last.get("views"))


class Bare(Strategy):
    name = "bare"


def test_tally_adds_updates_and_round_trips_through_a_dict():
    tally = Tally().add(UpdateInfo(grown=3, pruned=1, extra=dict(alive=np.int32(7))))
    tally = tally.add(UpdateInfo(pruned=2, capacity_changed=True, extra=dict(alive=jnp.int32(5))))
    assert (tally.updates, tally.grown, tally.pruned, tally.capacity_changes) == (2, 3, 3, 1)
    assert tally.last == {"alive": 5} and type(tally.last["alive"]) is int
    record = json.loads(json.dumps(tally.as_dict()))
    assert Tally.from_dict(record) == tally


def test_the_optional_hooks_do_nothing_by_default():
    bare, tally = Bare(), Tally()
    assert bare.before_first_update(Probe(step=1, render_ms_per_view=lambda: 1 / 0)) == {}  # the probe is not used
    assert bare.log_values(tally) == {} and bare.results(tally) == {}
    assert UpdateInfo() == UpdateInfo(grown=0, pruned=0, capacity_changed=False, extra={})


def test_the_built_in_strategies_are_strategies_and_the_shell_names_none_of_them():
    cfg = compose_config(["prune.strategy=feature_aware"])
    strategies = make_strategies(cfg)
    assert [s.name for s in strategies] == ["scaffold", "feature_prune"]
    assert all(Strategy in type(s).__mro__ for s in strategies)  # they inherit the no-op hooks
    from cusgs_jax.app import loop, session

    source = "".join(inspect.getsource(module) for module in (run_module, session, loop))  # the run's shell
    for strategy in strategies:
        assert type(strategy).__name__ not in source and f'"{strategy.name}"' not in source


@pytest.mark.slow  # end to end, ~20 s: in .ci/run's -m slow pass, out of the default run (kept under 8 minutes)
def test_a_strategy_defined_outside_the_package_is_trained_and_recorded(tmp_path):
    scene = generate_demo_scene(tmp_path / "scene", width=40, height=30, num_views=4, num_points=1500)
    cfg = compose_config([f"data.path={scene}", "train.iterations=4", "train.log_every=1", "train.progress=false",
                          "eval.every=0", "eval.save_renders=false", "train.checkpoint_every=0", "prune=none",
                          "model.n_offsets=4", "model.latent_dim=8", "model.hidden=16", "model.appearance_dim=8"])
    toy = CountViews()
    result = run_module.run(cfg, tmp_path / "run", extra_strategies=(toy,))

    assert toy.probed == [2]  # once, before its first update (after 2 steps), not again at step 4
    finite_views = 4 - result.skipped_updates
    tally = result.densify["count_views"]
    assert tally["updates"] == 2 and tally["grown"] == tally["pruned"] == 0 and tally["last"] == {"views": finite_views}
    assert tally["values"]["first_step"] == 2 and tally["values"]["render_ms"] > 0
    assert result.strategies["counted_views"] == finite_views  # its results hook
    assert "scaffold" in result.densify  # the configured strategies are recorded the same way
    # the keys every run had keep their values without feature-aware pruning
    assert result.render_ms_before_prune is None
    assert result.prune["strategy"] == "none" and (result.prune["passes"], result.prune["pruned"]) == (0, 0)
    assert json.loads((tmp_path / "run" / "eval.json").read_text())["densify"] == result.densify

    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4]
    assert [r["count_views_updates"] for r in rows] == [0, 1, 1, 2]  # its log_values hook
    assert [r["densify"]["count_views"]["updates"] for r in rows] == [0, 1, 1, 2]
    assert rows[-1]["densify"]["count_views"]["last"] == {"views": finite_views}
    assert all(r["pruned"] == 0 for r in rows)
