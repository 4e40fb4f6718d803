"""benchmarks/compile_overlap.py on the tiny run: both ways are timed, in turn, and the ratio is theirs."""

from __future__ import annotations

import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "benchmarks"))
import compile_overlap  # noqa: E402

from cusgs_jax.testing.runs import TINY  # noqa: E402


@pytest.mark.slow  # three step compiles of the tiny model: in .ci/run's -m slow pass
def test_the_compile_beside_the_steps_and_the_one_before_them_are_both_timed(tiny_scene):
    result = compile_overlap.main([f"data.path={tiny_scene}", *TINY], steps=2, rounds=1)
    assert result["backend"] == "cpu" and set(result["totals"]) == {"alone", "beside"}
    for way in ("alone", "beside"):
        assert result[way]["compile_s"] > 0 and result[way]["steps_s"] > 0
        assert result[way]["total_s"] >= result[way]["steps_s"]
    assert result["beside_over_alone"] == pytest.approx(result["beside"]["total_s"] / result["alone"]["total_s"], rel=0.02)
