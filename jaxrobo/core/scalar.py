"""Python floats as an array module: ``FLOATS`` is the ``xp`` a task's per-coordinate functions take on one env's
float64 scalars: when one env steps on the host (:class:`jaxrobo.interop.gym_adapter.JaxroboEnv` with
``engine="numpy"``), in a native-MuJoCo port (``envs/*/native.py``: the quadcopter's controller 30 times per control
step) and in an exported policy's runner (:mod:`jaxrobo.interop.numpy_policy`, which ``jaxrobo export`` writes out
with this module in it: it imports nothing but the standard library).

One env's state is a handful of numbers; as Python floats (IEEE float64) each operation costs tens of nanoseconds,
where a numpy function on a 0-d value costs about a microsecond and a JAX call more. The values equal numpy's to
float64 round-off (numpy's vector loops take ``atan2``/``asin`` from another implementation). Only the functions
those per-coordinate functions use are here. ``minimum``/``maximum`` are Python's ``min``/``max``, which do not
propagate a NaN as ``jnp`` does: a host step checks its state for non-finite values itself; ``where`` picks with
Python's ``if`` (a scalar condition), and a comparison has no ``~`` (a Python bool's is an integer's).
:func:`straight_line` writes such a function out once as plain arithmetic, for a host loop that calls it every step.
"""
from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any, Callable, Sequence

def _clip(x: float, low: float, high: float) -> float:
    return min(max(x, low), high)


#: ``xp`` over Python floats: :mod:`math` and the built-ins.
FLOATS = SimpleNamespace(sin=math.sin, cos=math.cos, minimum=min, maximum=max,
                         where=lambda cond, a, b: a if cond else b, clip=_clip, abs=abs, sqrt=math.sqrt,
                         arctan2=math.atan2, arcsin=math.asin)


class _Value:
    """A number of a function being written out by :func:`straight_line`: its name in the generated code."""

    __slots__ = ("code", "lines")

    def __init__(self, code: str, lines: list[str]):
        self.code, self.lines = code, lines

    def __bool__(self) -> bool:
        raise TypeError("straight_line: the function branches on a value it computes; only straight-line code "
                        "(branches on constants) can be written out")

    __add__ = lambda a, b: _emit(a, "{} + {}", a, b)  # noqa: E731
    __radd__ = lambda a, b: _emit(a, "{} + {}", b, a)  # noqa: E731
    __sub__ = lambda a, b: _emit(a, "{} - {}", a, b)  # noqa: E731
    __rsub__ = lambda a, b: _emit(a, "{} - {}", b, a)  # noqa: E731
    __mul__ = lambda a, b: _emit(a, "{} * {}", a, b)  # noqa: E731
    __rmul__ = lambda a, b: _emit(a, "{} * {}", b, a)  # noqa: E731
    __truediv__ = lambda a, b: _emit(a, "{} / {}", a, b)  # noqa: E731
    __rtruediv__ = lambda a, b: _emit(a, "{} / {}", b, a)  # noqa: E731
    __neg__ = lambda a: _emit(a, "-{}", a)  # noqa: E731
    # Comparisons give a value the generated code holds (a bool), for ``where``; no ``==``: a value stays hashable.
    __lt__ = lambda a, b: _emit(a, "{} < {}", a, b)  # noqa: E731
    __le__ = lambda a, b: _emit(a, "{} <= {}", a, b)  # noqa: E731
    __gt__ = lambda a, b: _emit(a, "{} > {}", a, b)  # noqa: E731
    __ge__ = lambda a, b: _emit(a, "{} >= {}", a, b)  # noqa: E731


def _code(v: Any) -> str:
    if isinstance(v, _Value):
        return v.code
    if isinstance(v, (bool, int, float)) and math.isfinite(v):
        return f"({float(v)!r})"  # repr round-trips a float exactly
    raise TypeError(f"straight_line: cannot write out the constant {v!r} ({type(v).__name__})")


def _emit(owner: _Value, template: str, *args: Any) -> _Value:
    name = f"t{len(owner.lines)}"
    owner.lines.append(f"{name} = " + template.format(*map(_code, args)))
    return _Value(name, owner.lines)


def _call(fn: str) -> Callable[..., Any]:
    def call(*args: Any) -> Any:
        owner = next(a for a in args if isinstance(a, _Value))
        return _emit(owner, fn + "(" + ", ".join("{}" for _ in args) + ")", *args)
    return call


def _where(cond: Any, a: Any, b: Any) -> Any:
    owner = next(v for v in (cond, a, b) if isinstance(v, _Value))
    return _emit(owner, "{} if {} else {}", a, cond, b)  # both sides are computed first, as an array's where does


#: The ``xp`` :func:`straight_line` runs a function with: :data:`FLOATS`' functions, written out.
_WRITING = SimpleNamespace(sin=_call("_sin"), cos=_call("_cos"), minimum=_call("_min"), maximum=_call("_max"),
                           sqrt=_call("_sqrt"), arctan2=_call("_atan2"), arcsin=_call("_asin"), abs=_call("_abs"),
                           where=_where, clip=lambda x, low, high: _WRITING.minimum(_WRITING.maximum(x, low), high))


def straight_line(fn: Callable[..., Sequence[Any]], names: Sequence[str]) -> Callable[..., tuple[float, ...]]:
    """``fn(xp, *args)`` over Python floats as one generated function of ``args`` (named ``names``), with its calls,
    loops and constant lookups run once here: the same operations in the same order as ``fn(FLOATS, *args)``,
    hence the same floats bit for bit, at the cost of the arithmetic alone. ``fn`` returns a sequence of values;
    it may branch on constants but not on the values it computes (a TypeError says so): a choice between computed
    values is ``xp.where(cond, a, b)``, written out as a conditional expression."""
    lines: list[str] = []
    out = fn(_WRITING, *(_Value(n, lines) for n in names))
    body = "\n".join(f"    {line}" for line in lines)
    src = f"def generated({', '.join(names)}):\n{body}\n    return ({''.join(_code(v) + ', ' for v in out)})\n"
    scope = {"_sin": math.sin, "_cos": math.cos, "_min": min, "_max": max, "_sqrt": math.sqrt, "_atan2": math.atan2,
             "_asin": math.asin, "_abs": abs}
    exec(compile(src, f"<straight_line {getattr(fn, '__qualname__', fn)}>", "exec"), scope)  # noqa: S102
    return scope["generated"]
