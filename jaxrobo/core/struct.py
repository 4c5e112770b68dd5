"""Frozen dataclasses that are JAX pytrees, and fields that carry their own validation rules.

Every parameter a user can set (from YAML, the CLI or ``jaxrobo.make(**overrides)``) is declared once, with
its range or allowed values, by :func:`param`; :mod:`jaxrobo.core.config` validates against these declarations, so
the rules live beside the value they guard.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence, TypeVar

T = TypeVar("T")

_RULES = "jaxrobo_rules"

#: Upper bound of every declared integer field that gives none: values become int32 arrays (counters, step
#: limits, indices) or shapes, so anything larger would wrap around or fail deep inside a compile.
INT32_MAX = 2**31 - 1


#: Every class :func:`pytree_dataclass` made, in order (:mod:`jaxrobo.speed.reuse` names them for ``jax.export``).
DATACLASSES: list[type] = []


def pytree_dataclass(cls: type[T]) -> type[T]:
    """A frozen dataclass registered as a pytree; fields declared with ``static=True`` become treedef metadata."""
    import jax  # here, not at the top: the rules and :class:`Rule` (config validation, ``import jaxrobo``) need no JAX

    cls = dataclasses.dataclass(frozen=True)(cls)
    data, meta = [], []
    for f in dataclasses.fields(cls):
        (meta if f.metadata.get("static", False) else data).append(f.name)
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    cls.replace = lambda self, **kw: dataclasses.replace(self, **kw)  # type: ignore[attr-defined]
    DATACLASSES.append(cls)
    return cls


@dataclasses.dataclass(frozen=True)
class Rule:
    """What a user-settable field accepts: a type, an optional closed range and an optional set of choices."""

    kind: type
    low: float | None = None
    high: float | None = None
    choices: Sequence[Any] | None = None
    doc: str = ""
    unit: str = ""
    low_open: bool = False  # True: the value must be strictly greater than ``low``
    optional: bool = False  # None is allowed (the field's default is None: "not given")
    pair: bool = False  # a ``[low, high]`` range: two numbers, each within ``low``..``high``, the first <= the second
    within: tuple[str, str] | None = None  # two fields of the same dataclass whose values bound this one's

    def describe(self) -> str:
        if self.pair:
            return (f"a range [low, high] with {self.low} <= low <= high <= {self.high}"
                    f"{' ' + self.unit if self.unit else ''}")
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        kind = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
                tuple: "a list"}.get(self.kind, str(self.kind))
        lo = "" if self.low is None else f"{'>' if self.low_open else '>='} {self.low}"
        hi = "" if self.high is None else f"<= {self.high}"
        bounds = " and ".join(b for b in (lo, hi) if b)
        return f"{kind}{' ' + bounds if bounds else ''}{' ' + self.unit if self.unit else ''}"


def param(
    default: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    choices: Sequence[Any] | None = None,
    static: bool = False,
    low_open: bool = False,
    doc: str = "",
    unit: str = "",
    kind: type | None = None,
    default_factory: Callable[[], Any] | None = None,
    within: tuple[str, str] | None = None,
    host_only: bool = False,
) -> Any:
    """Declare a user-settable field. ``static`` fields select code paths or shapes; the rest are traced leaves.
    ``within=(lo, hi)``: the value must also lie between the values of the fields ``lo`` and ``hi`` (a start
    position inside the track), checked with the whole dataclass (:func:`jaxrobo.core.config.check_relations`).
    ``host_only``: only host code reads the value (a seed, which makes the first key: programs get the key as an
    argument), so a program traced under one value serves every other: a kept trace's key leaves it out
    (:func:`jaxrobo.speed.reuse.describe`)."""
    kind = kind or type(default)
    if kind is int and high is None:
        high = INT32_MAX
    rule = Rule(kind, low, high, tuple(choices) if choices is not None else None, doc, unit, low_open,
                optional=default is None and default_factory is None, within=within)
    meta = {"static": static, _RULES: rule, **({"host_only": True} if host_only else {})}
    if default_factory is not None:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def range_param(default: tuple[float, float], *, low: float, high: float, doc: str = "", unit: str = "") -> Any:
    """Declare a traced ``(low, high)`` range (a domain-randomisation range, :mod:`jaxrobo.task.randomise`): the
    config accepts ``[low, high]`` with ``low <= high``, both within the declared ``low``..``high``; a sweep may vary
    it (a ``[2]`` array per row)."""
    rule = Rule(tuple, float(low), float(high), None, doc, unit, pair=True)
    return dataclasses.field(default=tuple(float(v) for v in default), metadata={"static": False, _RULES: rule})


def static_field(default: Any = dataclasses.MISSING, **kw: Any) -> Any:
    """A pytree field that is metadata (hashed into the treedef), not a traced leaf."""
    return dataclasses.field(default=default, metadata={"static": True}, **kw)


def rules(cls_or_obj: Any) -> dict[str, Rule]:
    """The validation rule of every user-settable field of a dataclass."""
    return {f.name: f.metadata[_RULES] for f in dataclasses.fields(cls_or_obj) if _RULES in f.metadata}


def ordered_pairs(cls_or_obj: Any) -> list[tuple[str, str]]:
    """The numeric fields that bound a range by name: two names that differ only in a ``min`` token for a ``max``
    one (``min_pole_angle``/``max_pole_angle``, ``goal_min_dist``/``goal_max_dist``, ``elbow_min``/``elbow_max``);
    the first must not exceed the second. Derived from the names, so a new task's pairs need no declaration."""
    numeric = [n for n, r in rules(cls_or_obj).items() if r.kind in (int, float) and not r.pair]
    pairs = []
    for name in numeric:
        tokens = name.split("_")
        for i, token in enumerate(tokens):
            other = "_".join(tokens[:i] + ["max"] + tokens[i + 1:])
            if token == "min" and other in numeric:
                pairs.append((name, other))
    return pairs
