"""YAML configuration: load with safe loading, validate against the declared fields, merge overrides.

The seed keeps environment parameters and algorithm parameters in YAML files loaded at run time; jaxrobo does
the same (``envs/configs/*.yaml``, ``agents/configs/*.yaml``) and checks every value *before* anything compiles:
an unknown key, a wrong type or an out-of-range value raises :class:`ConfigError` naming the key and what it
accepts.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
from typing import Any, Iterable, Mapping

import yaml

from jaxrobo.struct import Rule, rules


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


def load_yaml(path: str) -> dict[str, Any]:
    """Read a YAML mapping with ``yaml.safe_load`` (no arbitrary objects)."""
    if not os.path.exists(path):
        raise ConfigError(f"config file not found: {path}")
    with open(path) as f:
        data = yaml.safe_load(f)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of key: value at the top level, got {type(data).__name__}")
    return data


def coerce(key: str, value: Any, rule: Rule, where: str = "") -> Any:
    """Check one value against its rule; ints are accepted for floats. Returns the value in the rule's type."""
    loc = f"{where}: " if where else ""
    kind = rule.kind
    if value is None and (rule.optional or (rule.choices is not None and None in rule.choices)):
        return None
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
    elif kind is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
        value = int(value)
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{loc}{key}={value!r}: must be finite")
    elif kind is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{loc}{key}={value!r}: expected a list")
        value = tuple(value)
    elif kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
    if rule.choices is not None and value not in rule.choices:
        raise ConfigError(f"{loc}{key}={value!r}: allowed values are {rule.describe()[7:]}")
    if kind in (int, float):
        if rule.low is not None and (value < rule.low or (rule.low_open and value == rule.low)):
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
        if rule.high is not None and value > rule.high:
            raise ConfigError(f"{loc}{key}={value!r}: expected {rule.describe()}")
    return value


def unknown_key(key: str, known: Iterable[str], where: str = "") -> ConfigError:
    known = sorted(known)
    close = difflib.get_close_matches(key, known, n=3)
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    loc = f"{where}: " if where else ""
    return ConfigError(f"{loc}unknown key {key!r}{hint}; allowed keys: {', '.join(known)}")


def split_and_validate(values: Mapping[str, Any], *targets: type, where: str = "") -> list[dict[str, Any]]:
    """Route each key to the first dataclass in ``targets`` that declares it, validating it there."""
    tables = [rules(t) for t in targets]
    out: list[dict[str, Any]] = [{} for _ in targets]
    for key, value in values.items():
        for i, table in enumerate(tables):
            if key in table:
                out[i][key] = coerce(key, value, table[key], where)
                break
        else:
            raise unknown_key(key, [k for t in tables for k in t], where)
    return out


def build(cls: type, values: Mapping[str, Any], where: str = "") -> Any:
    """Instantiate a params/options dataclass from validated values (defaults for the rest)."""
    (checked,) = split_and_validate(values, cls, where=where)
    return cls(**checked)


def parse_value(text: str) -> Any:
    """A command-line value as YAML reads it: ``0.3`` → float, ``true`` → bool, ``[1, 2]`` → list."""
    return yaml.safe_load(text)


def parse_overrides(pairs: Iterable[str]) -> dict[str, Any]:
    """``["alpha=0.3", "env.pos_step=0.02"]`` → ``{"alpha": 0.3, "env.pos_step": 0.02}``."""
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE")
        key, text = pair.split("=", 1)
        out[key.strip()] = parse_value(text)
    return out


def as_dict(obj: Any) -> dict[str, Any]:
    """A params/options dataclass as plain Python values (for YAML/JSON output)."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        try:
            import numpy as np

            arr = np.asarray(v)
            v = arr.tolist() if arr.ndim else arr.item()
        except Exception:  # noqa: BLE001 - strings and other plain values pass through
            pass
        out[f.name] = v
    return out
