"""Reading traced programs: which matmuls run at which precision (tests only).

The CPU ignores ``dot_general``'s precision, so a CPU test cannot see TF32 in the numbers; it can
see it in the program. :func:`dot_precisions` traces a function and lists every ``dot_general``
(in nested jaxprs too: jit, scan, while, cond, custom_jvp/vjp, remat) with its precision and
where in the source it was written.
"""

from __future__ import annotations

import dataclasses

import jax
from jax.extend import core as jex_core


@dataclasses.dataclass(frozen=True)
class Dot:
    """One ``dot_general`` of a traced program."""

    precision: object  # the eqn's ``precision`` param: None, a Precision or a pair of them
    shapes: tuple  # the operands' shapes
    where: str  # "file:line (function)" of the innermost frame inside cusgs_jax, or "?"

    @property
    def highest(self) -> bool:
        """Both operands at :data:`jax.lax.Precision.HIGHEST`."""
        p = self.precision
        pair = p if isinstance(p, tuple) else (p, p)
        return all(q == jax.lax.Precision.HIGHEST for q in pair)


def _sub_jaxprs(value):
    if isinstance(value, jex_core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jex_core.Jaxpr):
        yield value
    elif isinstance(value, (tuple, list)):
        for item in value:
            yield from _sub_jaxprs(item)


def _where(eqn) -> str:
    try:
        frames = eqn.source_info.traceback.frames
    except AttributeError:
        return "?"
    for frame in frames:  # innermost first
        if "/cusgs_jax/" in frame.file_name and "/testing/" not in frame.file_name:
            return f"{frame.file_name.split('/cusgs_jax/')[-1]}:{frame.line_num} ({frame.function_name})"
    return "?"


def _walk(jaxpr, out: list) -> None:
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            out.append(Dot(eqn.params.get("precision"), tuple(tuple(v.aval.shape) for v in eqn.invars), _where(eqn)))
        for value in eqn.params.values():
            for sub in _sub_jaxprs(value):
                _walk(sub, out)
        # custom_jvp/vjp keep their rules as callables: trace-time thunks are not walked, but the
        # primal jaxpr (``call_jaxpr`` / ``fun_jaxpr``) is a param and is walked above


def dot_precisions(fn, *args, **kwargs) -> list[Dot]:
    """Every ``dot_general`` of ``jax.make_jaxpr(fn)(*args, **kwargs)``, nested ones included."""
    closed = jax.make_jaxpr(fn)(*args, **kwargs)
    out: list[Dot] = []
    _walk(closed.jaxpr, out)
    return out


def loose_dots(fn, *args, **kwargs) -> list[Dot]:
    """The ``dot_general`` s of ``fn`` that are not at HIGHEST precision (empty when all are)."""
    return [dot for dot in dot_precisions(fn, *args, **kwargs) if not dot.highest]
