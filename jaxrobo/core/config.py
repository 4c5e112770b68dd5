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
import re
import stat
from typing import Any, Iterable, Mapping

import numpy as np
import yaml

from jaxrobo.core.struct import Rule, rules


#: The smallest normal and the largest finite float32 (``np.finfo(np.float32).tiny`` / ``.max``).
FLOAT32_TINY, FLOAT32_MAX = 1.1754943508222875e-38, 3.4028234663852886e38


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` (no Python objects) that also refuses duplicate keys and reads every float syntax.

    YAML 1.1 reads ``1e-3`` (no dot) as a string; here it is the number a user means. A mapping that gives the
    same key twice would silently keep the last value, so it is an error naming the key and both lines.
    """


_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))


def _mapping_without_duplicates(loader: StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            first = seen.get(key)
        except TypeError:  # an unhashable key (a list or mapping used as a key)
            raise ConfigError(f"line {key_node.start_mark.line + 1}: a key must be a plain value, "
                              f"got {key!r}") from None
        if first is not None:
            raise ConfigError(f"duplicate key {key!r} (lines {first} and {key_node.start_mark.line + 1}): "
                              "give each key once")
        seen[key] = key_node.start_mark.line + 1
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_duplicates)

#: YAML types that SafeLoader builds and a config never holds (a config is JSON's values: null, booleans, numbers,
#: strings, lists, mappings): a date in a hand-edited config.yaml would reach a field as a ``datetime``.
_NOT_CONFIG_TYPES = {"timestamp": "a date or time", "set": "a set", "binary": "binary data",
                     "omap": "an ordered mapping", "pairs": "a list of pairs"}


def _refuse(what: str):
    def construct(loader: StrictLoader, node: yaml.Node) -> Any:
        value = node.value if isinstance(node, yaml.ScalarNode) else f"!!{node.tag.rpartition(':')[2]}"
        raise ConfigError(f"line {node.start_mark.line + 1}: {value!s:.40} is {what}, not a value a config holds "
                          "(null, booleans, numbers, strings, lists, mappings); quote it to give a string")
    return construct


for _tag, _what in _NOT_CONFIG_TYPES.items():
    StrictLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _refuse(_what))

#: Limits on what a YAML file may hold (configs are small: a run's config.yaml is ~2 KB, ~150 nodes). A file read
#: back is hostile: a 24 MB list takes minutes to parse, an alias bomb grows exponentially, deep nesting
#: overflows the stack. Bytes are checked before parsing, nesting and nodes while composing.
YAML_MAX_BYTES = 1 << 20
YAML_MAX_DEPTH = 32
YAML_MAX_NODES = 100_000


def _compose_node(loader: StrictLoader, parent: Any, index: Any) -> Any:
    if loader.check_event(yaml.events.AliasEvent):
        mark = loader.peek_event().start_mark
        raise ConfigError(f"line {mark.line + 1}: YAML aliases (*name) are not accepted; write the value out")
    loader._jaxrobo_depth = depth = getattr(loader, "_jaxrobo_depth", 0) + 1
    loader._jaxrobo_nodes = nodes = getattr(loader, "_jaxrobo_nodes", 0) + 1
    try:
        if depth > YAML_MAX_DEPTH:
            raise ConfigError(f"line {loader.peek_event().start_mark.line + 1}: nested deeper than "
                              f"{YAML_MAX_DEPTH} levels")
        if nodes > YAML_MAX_NODES:
            raise ConfigError(f"more than {YAML_MAX_NODES} values")
        return yaml.composer.Composer.compose_node(loader, parent, index)
    finally:
        loader._jaxrobo_depth = depth - 1


StrictLoader.compose_node = _compose_node  # type: ignore[method-assign]


#: Bits of the largest integer a config may hold: none of its values needs more, and a larger one fails later
#: where it becomes a float (past float's range) or is printed (past Python's 4,300 digits).
INT_MAX_BITS = 64


def _check_ints(data: Any) -> None:
    """ConfigError for an integer of more than :data:`INT_MAX_BITS` bits anywhere in parsed YAML."""
    stack = [data]
    while stack:
        x = stack.pop()
        if isinstance(x, dict):
            stack.extend(x.keys())
            stack.extend(x.values())
        elif isinstance(x, (list, tuple)):
            stack.extend(x)
        elif isinstance(x, int) and not isinstance(x, bool) and x.bit_length() > INT_MAX_BITS:
            raise ConfigError(f"an integer of {x.bit_length():,} bits; a config's numbers are at most "
                              f"{INT_MAX_BITS}-bit integers or floats")


def parse_yaml(text: str, where: str) -> Any:
    """YAML text through :class:`StrictLoader`; any syntax error, unknown tag, duplicate key, alias, or a text
    past :data:`YAML_MAX_BYTES` / :data:`YAML_MAX_DEPTH` / :data:`YAML_MAX_NODES` is a ConfigError."""
    if len(text) > YAML_MAX_BYTES:
        raise ConfigError(f"{where}: {len(text):,} characters, more than a config holds (at most "
                          f"{YAML_MAX_BYTES:,})")
    try:
        data = yaml.load(text, Loader=StrictLoader)  # noqa: S506 - StrictLoader is a SafeLoader
        _check_ints(data)
        return data
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
    except (ValueError, OverflowError) as err:  # e.g. an integer past Python's 4,300 digits, as PyYAML converts it
        why = "an integer too long to read" if "digits" in str(err) else f"a value that cannot be read ({err})"
        raise ConfigError(f"{where}: holds {why}; a config's numbers are at most {INT_MAX_BITS}-bit integers or "
                          "floats") from None
    except yaml.YAMLError as err:
        # e.g. "could not determine a constructor for the tag '!!python/object...'" or a syntax error with its line
        msg = " ".join(str(err).split())
        raise ConfigError(f"{where}: not valid YAML (safe subset only): {msg}") from None


def check_regular(path: str, where: str | None = None) -> None:
    """Refuse (:class:`ConfigError` naming ``where`` or the path) to read ``path`` when it exists and is not a
    regular file (after symlinks): a FIFO would hang the read, a device (``/dev/zero``) never end it. A missing
    file is left to the reader (its own FileNotFoundError)."""
    try:
        st = os.stat(path)
    except OSError:
        return
    if not stat.S_ISREG(st.st_mode):
        what = "a directory" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, socket or device)"
        raise ConfigError(f"{where or path}: is {what}; expected a regular file")


def parse_json(text: str | bytes) -> Any:
    """``json.loads(text)``, with text nested past Python's recursion limit a ValueError like any other malformed
    JSON (``json`` raises RecursionError there): every file jaxrobo reads back as JSON is hostile input."""
    import json

    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None


def shown(value: Any, limit: int = 200) -> str:
    """``repr(value)`` for a message, at most ``limit`` characters (an integer past Python's 4,300 digits, whose
    repr raises, by its size)."""
    try:
        text = repr(value)
    except ValueError:
        return f"<an integer of {value.bit_length():,} bits>" if isinstance(value, int) else f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def load_yaml(path: str, where: str | None = None) -> dict[str, Any]:
    """Read a YAML mapping safely (no arbitrary objects, no duplicate keys, no aliases, bounded size and
    nesting: :func:`parse_yaml`); ConfigError starting with ``where`` (default: the path) on anything else."""
    where = path if where is None else where
    if not os.path.exists(path):
        raise ConfigError(f"config file not found: {path}")
    check_regular(path, where)  # a FIFO would hang the read, a device never end it
    try:
        with open(path, "rb") as f:
            raw = f.read(YAML_MAX_BYTES + 1)  # never more than the cap, whatever the file's size
    except OSError as err:
        raise ConfigError(f"{where}: cannot be read ({err.strerror or err})") from None
    if len(raw) > YAML_MAX_BYTES:
        raise ConfigError(f"{where}: larger than {YAML_MAX_BYTES:,} bytes, more than a config holds")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{where}: cannot be read as a text file (not UTF-8 at byte {err.start})") from None
    if "\0" in text:
        raise ConfigError(f"{where}: cannot be read as a text file (it holds NUL bytes)")
    data = parse_yaml(text, where)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of key: value at the top level, got {type(data).__name__}")
    return data


def coerce(key: str, value: Any, rule: Rule, where: str = "") -> Any:
    """Check one value against its rule; ints are accepted for floats. Returns the value in the rule's type."""
    loc = f"{where}: " if where else ""
    kind = rule.kind
    if value is None and (rule.optional or (rule.choices is not None and None in rule.choices)):
        return None
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
    elif kind is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
        value = int(value)
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
        try:
            value = float(value)
        except OverflowError:  # an int past float's range
            raise ConfigError(f"{loc}{key}={shown(value)}: is inf in float32, the precision a run computes in; its "
                              f"magnitude must be at most {FLOAT32_MAX:.4g}") from None
        if not math.isfinite(value):
            raise ConfigError(f"{loc}{key}={shown(value)}: must be finite")
        # Values become float32 arrays: one that is 0, subnormal (flushed to 0 on most devices) or inf there is
        # not the value given ("alpha=1e-320" would pass "> 0" and train nothing).
        if value != 0 and not FLOAT32_TINY <= abs(value) <= FLOAT32_MAX:
            big = abs(value) > FLOAT32_MAX
            raise ConfigError(f"{loc}{key}={shown(value)}: is {'inf' if big else '0'} in float32, the precision a run "
                              f"computes in; its magnitude must be {'at most' if big else 'at least'} "
                              f"{FLOAT32_MAX if big else FLOAT32_TINY:.4g}")
    elif kind is tuple and rule.pair:
        return _range(key, value, rule, loc)
    elif kind is tuple:
        if not isinstance(value, (list, tuple)):
            doc = f" ({rule.doc})" if rule.doc else ""
            raise ConfigError(f"{loc}{key}={shown(value)}: expected a list{' or null' if rule.optional else ''}{doc}")
        value = tuple(value)
    elif kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
    if rule.choices is not None and value not in rule.choices:
        raise ConfigError(f"{loc}{key}={shown(value)}: allowed values are {rule.describe()[7:]}")
    if kind in (int, float):
        if rule.low is not None and (value < rule.low or (rule.low_open and value == rule.low)):
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
        if rule.high is not None and value > rule.high:
            raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
    return value


def _finite(v: float) -> bool:
    """``math.isfinite(v)``, False for an int past float's range (where it raises)."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _range(key: str, value: Any, rule: Rule, loc: str) -> tuple[float, float]:
    """A ``[low, high]`` range (:func:`jaxrobo.core.struct.range_param`) as a tuple of two floats, or ConfigError."""
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and _finite(v) for v in value)
    if not ok:
        raise ConfigError(f"{loc}{key}={shown(value)}: expected {rule.describe()}")
    low, high = float(value[0]), float(value[1])
    if low > high:
        raise ConfigError(f"{loc}{key}={shown(value)}: low {low} > high {high}; expected {rule.describe()}")
    if low < rule.low or high > rule.high:
        raise ConfigError(f"{loc}{key}={shown(value)}: outside the physical limits; expected {rule.describe()}")
    return (low, high)


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
    if not isinstance(values, Mapping):
        loc = f"{where}: " if where else ""
        raise ConfigError(f"{loc}expected a mapping of key: value, got {type(values).__name__} {values!r}")
    for key, value in values.items():
        if not isinstance(key, str):
            raise unknown_key(repr(key), [k for t in tables for k in t], where)
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


def parse_value(text: str, key: str = "value") -> Any:
    """A command-line value as YAML reads it: ``0.3`` or ``1e-3`` → float, ``true`` → bool, ``[1, 2]`` → list."""
    return parse_yaml(text, f"--set {key}")


def check_relations(obj: Any, where: str) -> None:
    """The relations between fields of a built Options/Params dataclass that no single field's rule can see: each
    :func:`~jaxrobo.core.struct.ordered_pairs` ``(min, max)`` in order, and each ``within=(lo, hi)`` field
    between those two fields' values; a ConfigError naming the fields and values. Per-row values (a sweep's
    arrays) are checked row by row; traced values (inside a jitted function) are left alone."""
    from jaxrobo.core.struct import ordered_pairs, rules

    def values(name: str):
        try:
            return np.asarray(getattr(obj, name), np.float64)
        except Exception:  # noqa: BLE001 - a tracer: not a concrete value to check
            return None

    def show(a) -> str:
        return f"{float(a.flat[0]):g}" if a.size == 1 else f"{a.tolist()}"

    for lo, hi in ordered_pairs(obj):
        a, b = values(lo), values(hi)
        if a is not None and b is not None and np.any(a > b):
            raise ConfigError(f"{where}: {lo}={show(a)} is above {hi}={show(b)}; {lo} must be <= {hi}")
    for name, rule in rules(obj).items():
        if rule.within is None:
            continue
        v, (lo, hi) = values(name), rule.within
        a, b = values(lo), values(hi)
        if v is not None and a is not None and b is not None and np.any((v < a) | (v > b)):
            raise ConfigError(f"{where}: {name}={show(v)} is outside [{lo}, {hi}] = [{show(a)}, {show(b)}]")


def _check_array(key: str, value: Any, rule: Rule, loc: str) -> None:
    """Every element of a concrete array value (a parameter given as a JAX or numpy array, a sweep's rows) against
    ``rule``, as :func:`coerce` checks one number; bounds compared in the array's own dtype, so a float32 copy of an
    accepted value (0.1 is 0.100000001 in float32) is accepted too."""
    a = np.asarray(value)
    if rule.kind in (str, bool) or (rule.kind is tuple and not rule.pair):
        return
    if a.dtype.kind not in "biuf" or a.dtype.kind == "b" or (rule.kind is int and a.dtype.kind == "f") \
            or (rule.pair and (a.ndim == 0 or a.shape[-1] != 2)):
        raise ConfigError(f"{loc}{key}: an array of {a.dtype} with shape {a.shape}: expected {rule.describe()}")
    bad = ~np.isfinite(a) if a.dtype.kind == "f" else np.zeros(a.shape, bool)
    if rule.choices is not None:
        bad |= ~np.isin(a, np.asarray(rule.choices, a.dtype))
    if rule.low is not None:
        low = np.asarray(rule.low).astype(a.dtype)
        bad |= (a <= low) if rule.low_open else (a < low)
    if rule.high is not None:
        bad |= a > np.asarray(rule.high).astype(a.dtype)
    if rule.pair:
        bad |= (a[..., 0] > a[..., 1])[..., None]
    if bad.any():
        # str of the array's own scalar: a float32 1.9 reads 1.9, not its float64 expansion 1.899999976158142
        first = ("[" + ", ".join(map(str, a.reshape(-1, 2)[bad.reshape(-1, 2).any(1)][0])) + "]" if rule.pair
                 else str(a[bad].flat[0]))
        raise ConfigError(f"{loc}{key}={first}: expected {rule.describe()}")


def check_fields(obj: Any, where: str) -> None:
    """A built Options/Params/config dataclass (one a Python caller made, not read through :func:`build`) checked as
    :func:`split_and_validate` and :func:`check_relations` check given values: every declared field against its
    rule, a value of the wrong type included (``n_envs=2.5``); array values element by element; traced values
    (inside a jitted function) are left alone. A ConfigError naming ``where``, the field and what it accepts."""
    loc = f"{where}: " if where else ""
    for name, rule in rules(obj).items():
        value = getattr(obj, name)
        if isinstance(value, (bool, int, float, str, list, tuple)) or value is None:
            coerce(name, value, rule, where)
            # coerce takes 2.0 for 2 (a file's number); a shape needs the int
            if rule.kind is int and value is not None and not isinstance(value, int):
                raise ConfigError(f"{loc}{name}={shown(value)}: expected {rule.describe()}")
            continue
        try:
            np.asarray(value)
        except Exception:  # noqa: BLE001 - a tracer (or an object that is no array): not a concrete value to check
            continue
        _check_array(name, value, rule, loc)
    check_relations(obj, where)


def parse_overrides(pairs: Iterable[str]) -> dict[str, Any]:
    """``["alpha=0.3", "env.pos_step=0.02"]`` → ``{"alpha": 0.3, "env.pos_step": 0.02}``."""
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE")
        key, text = pair.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"--set {pair!r}: expected KEY=VALUE (the key is empty)")
        if key in out:
            raise ConfigError(f"--set {key}: given twice ({out[key]!r} and {text!r}); give each key once")
        # ``alpha`` and ``agent.alpha`` name one value: one of the two would win silently.
        bare = _bare(key)
        for other in out:
            if _bare(other) == bare and bare in (key, other):
                raise ConfigError(f"--set {key}={text.strip()} and --set {other}={out[other]!r} name the same key; "
                                  "give it once")
        out[key] = parse_value(text, key)
    return out


def _bare(key: str) -> str:
    """A ``--set`` key without its ``env.`` / ``agent.`` section."""
    return key.split(".", 1)[1] if key.startswith(("env.", "agent.")) else key


def merge_flags(overrides: dict[str, Any], flags: Iterable[tuple[str, str, Any]]) -> dict[str, Any]:
    """Add command-line flags ``(key, flag, value)`` (value None: not given) to ``--set`` overrides; a key given
    both ways (``--n-envs 2 --set n_envs=3``, or ``agent.n_envs``) is refused rather than one silently winning."""
    for key, flag, value in flags:
        if value is None:
            continue
        for name in (key, f"agent.{key}"):
            if name in overrides:
                raise ConfigError(f"{key} given twice: {flag} {value} and --set {name}={overrides[name]!r}; "
                                  "give it once")
        overrides[key] = value
    return overrides


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


def flat_keys(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested mapping as ``{"outer.inner": value}`` (to name the keys where two configs differ)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flat_keys(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out
