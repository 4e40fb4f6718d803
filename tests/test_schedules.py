"""Schedules that never run (schedules.py): named with a value that runs, warned about once each."""

from __future__ import annotations

from cusgs_jax.config import Config


def _fixed(line: str) -> dict:
    """The ``e.g. group.key=value ...`` settings a warning proposes: {"prune": {"start": 100}, ...}."""
    changes: dict = {}
    for item in line.split("e.g. ", 1)[1].split():
        key, value = item.split("=")
        group, name = key.split(".")
        changes.setdefault(group, {})[name] = int(value)
    return changes


def test_schedules_that_never_run_are_named_with_a_value_that_runs():
    from cusgs_jax.schedules import idle_schedules, schedule_warnings

    assert schedule_warnings(Config()) == []
    short = Config().replace(train=dict(iterations=300))
    idle = idle_schedules(short)
    assert set(idle) == {"prune", "grow", "train.checkpoint_every"}
    assert idle["prune"] == "prune.start=500 is past train.iterations=300: no pruning pass runs; e.g. prune.start=100"
    assert idle["grow"].startswith("grow.start=400 is past train.iterations=300: no growing")
    assert idle["train.checkpoint_every"].startswith("train.checkpoint_every=1000 is not before train.iterations=300")
    for key, line in idle.items():  # the proposed values run
        assert key not in idle_schedules(short.replace(**_fixed(line))), line
    assert "prune" not in idle_schedules(short.replace(prune=dict(strategy="none")))  # no pruning asked for
    gap = Config().replace(prune=dict(start=250, stop=260))  # no multiple of the interval within [start, stop]
    assert idle_schedules(gap)["prune"].startswith("no multiple of prune.interval=100 falls in [prune.start=250")
    assert "prune" not in idle_schedules(gap.replace(**_fixed(idle_schedules(gap)["prune"])))
    curve = Config().replace(eval=dict(every=5000))
    assert schedule_warnings(curve) == ["eval.every=5000 is past train.iterations=3000: the held-out curve gets only "
                                        "its final point; e.g. eval.every=300"]
    assert schedule_warnings(Config().replace(eval=dict(every=0), train=dict(iterations=300, checkpoint_every=0),
                                              grow=dict(start=100), prune=dict(start=100))) == []


def test_schedule_warnings_are_logged_once_each(caplog):
    from cusgs_jax.schedules import warn_schedules

    with caplog.at_level("WARNING", logger="cusgs_jax"):
        lines = warn_schedules(Config().replace(train=dict(iterations=300)))
    assert [r.getMessage() for r in caplog.records if r.name == "cusgs_jax"] == lines and len(lines) == 3
