"""Validation helpers (checks.py): one ConfigError naming the option, its value and the fix."""

from __future__ import annotations

import dataclasses
import math

import pytest

from cusgs_jax.checks import at_least, finite_number, lists_to_tuples, require
from cusgs_jax.errors import ConfigError


def test_require_names_the_option_value_and_fix():
    require(True, "a.b", 3, "never raised")
    with pytest.raises(ConfigError, match=r"^a\.b=-1: must be >= 0; use a positive size$"):
        require(False, "a.b", -1, "must be >= 0", "use a positive size")


@pytest.mark.parametrize("value, ok", [(1, True), (2.5, True), (True, False), (math.nan, False), (math.inf, False),
                                       ("1", False), (None, False)])
def test_finite_number(value, ok):
    assert finite_number(value) is ok


def test_at_least_and_lists_to_tuples():
    @dataclasses.dataclass(frozen=True)
    class Group:
        size: float = 1.0
        names: object = dataclasses.field(default_factory=lambda: ["x", "y"])

    group = Group()
    at_least(group, "group", 0.5, "size")
    with pytest.raises(ConfigError, match=r"group\.size=0\.1: must be a number >= 0\.5"):
        at_least(Group(size=0.1), "group", 0.5, "size")
    lists_to_tuples(group)
    assert group.names == ("x", "y") and hash(group.names)
