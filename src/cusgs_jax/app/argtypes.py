"""argparse value types shared by the command-line tools (a bad value: argparse's message, exit 2)."""

from __future__ import annotations

import argparse
import math
import re
from typing import Callable


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An integer ≥ ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer ≥ {minimum}, got {text!r}")
        return value
    return parse


def number_in(low: float, high: float, *, include_high: bool = True) -> Callable[[str], float]:
    """A number in ``[low, high]`` (``[low, high)`` with ``include_high=False``)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (low <= value <= high and (include_high or value < high)):
            closing = "]" if include_high else ")"
            raise argparse.ArgumentTypeError(f"expected a number in [{low:g}, {high:g}{closing}, got {text!r}")
        return value
    return parse


def in_cli_terms(message: str, names: dict[str, str]) -> str:
    """``message`` (a :class:`~cusgs_jax.errors.UserError`'s, written in ``cusgs-train``'s option names)
    with each option of ``names`` replaced by what the tool calls it: ``{"data.path": "--scene"}`` turns
    ``data.path=/x`` into ``--scene /x`` and ``set data.path to`` into ``set --scene to``."""
    for option, flag in names.items():
        message = re.sub(rf"(?<![\w.-]){re.escape(option)}(?![\w])(=?)",
                         lambda m, flag=flag: flag + (" " if m.group(1) else ""), message)
    return message
