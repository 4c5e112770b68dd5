"""Which rows a sweep trains, checked before anything compiles: the swept keys, their points, the groups.

A swept key is routed as ``--set`` routes it (:func:`classify`); a grid (:func:`parse_grid`, :func:`grid_points`)
or a random sample (:func:`parse_ranges`, :func:`random_points`) gives the points; :func:`plan_groups` validates
them and groups them by the values that change shapes or code (one compiled program per group), and
:func:`plan_sweep` resolves every group's run into a :class:`SweepPlan` whose ``settings`` are what a saved sweep
state is compared with (:mod:`jaxrobo.training.sweep.state`).

Public surface: :data:`NOT_SWEPT`, :data:`KeyKind`, :func:`classify`, :func:`parse_grid`, :func:`parse_ranges`,
:func:`grid_points`, :func:`random_points`, :func:`plan_groups`, :class:`PlannedGroup`, :class:`SweepPlan`,
:func:`plan_sweep`.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import re
from typing import Any, Mapping, Sequence

import numpy as np

from jaxrobo.training import budget
from jaxrobo.core.config import ConfigError, check_relations, coerce, parse_value
from jaxrobo.task import randomise
from jaxrobo.training.run import KeyRoute, resolve, route
from jaxrobo.training.trainer import Trainer

NOT_SWEPT = ("seed",)  # the seed axis is --seeds


# ---- what a key is -------------------------------------------------------------------------------------------
#: A swept key as :func:`jaxrobo.training.run.route`, the router of ``--set``, places it: ``name`` (the field),
#: ``where`` (``"agent"``/``"env"``: a traced learner / env parameter, vmapped; ``"train"``/``"option"``: a static loop
#: setting / env option, one compiled group per value) and ``static``.
KeyKind = KeyRoute


def classify(env_id: str, key: str) -> KeyKind:
    """Where a swept key lives: :func:`jaxrobo.training.run.route` (learner and loop first, as ``--set`` does;
    ``env.``/``agent.`` force a side), the seed excepted (it is the ``--seeds`` axis)."""
    if isinstance(key, str) and (key.split(".", 1)[1] if key.startswith(("env.", "agent.")) else key) in NOT_SWEPT:
        raise ConfigError(f"--grid {key}: the seed is not a swept parameter; use --seeds N (and --seed BASE)")
    return route(env_id, key, where="sweep")


# ---- which points ----------------------------------------------------------------------------------------------
def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["alpha=0.1,0.3", "gamma=0.9"]`` → ``{"alpha": [0.1, 0.3], "gamma": [0.9]}``; a comma inside brackets
    belongs to a list value (a randomisation range: ``rand_mass=[1,1],[0.8,1.2]``)."""
    axes: dict[str, list[Any]] = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--grid {item!r}: expected KEY=V1,V2,...")
        key, text = (s.strip() for s in item.split("=", 1))
        if not text.strip():
            raise ConfigError(f"--grid {item!r}: no values after '='")
        parts = re.split(r",(?![^\[]*\])", text)  # a comma inside brackets belongs to a list value
        empty = [i + 1 for i, v in enumerate(parts) if not v.strip()]
        if empty:  # "0.1,,0.3" or a trailing comma: a value was left out, not meant to be skipped
            raise ConfigError(f"--grid {item!r}: value {empty[0]} of {len(parts)} is empty; give each value once, "
                              "separated by single commas")
        if key in axes:
            raise ConfigError(f"--grid {key}: given twice ({','.join(map(str, axes[key]))} and {text}); give each "
                              "key once, with all its values")
        axes[key] = [parse_value(v.strip(), key) for v in parts]
        twice = [i for i, v in enumerate(axes[key]) if v in axes[key][:i]]
        if twice:  # 0.1,0.10 or 0.1,0.1: the same configuration twice, its rows run and ranked as two (a typo)
            raise ConfigError(f"--grid {item!r}: value {axes[key][twice[0]]!r} is given twice; give each value once")
    return axes


def parse_ranges(items: Sequence[str]) -> dict[str, tuple[float, float, bool]]:
    """``["alpha=0.05:0.9", "epsilon_discount=0.99:0.9999:log"]`` → ``{key: (low, high, log)}``."""
    out: dict[str, tuple[float, float, bool]] = {}
    for item in items or []:
        key, _, text = item.partition("=")
        parts = text.split(":")
        if not _ or len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] not in ("log", "lin")):
            raise ConfigError(f"--range {item!r}: expected KEY=LOW:HIGH or KEY=LOW:HIGH:log")
        try:
            lo, hi = float(parts[0]), float(parts[1])
        except ValueError as err:
            raise ConfigError(f"--range {item!r}: LOW and HIGH must be numbers") from err
        log = len(parts) == 3 and parts[2] == "log"
        if not lo < hi or (log and lo <= 0):
            raise ConfigError(f"--range {item!r}: need LOW < HIGH{' and LOW > 0 for log' if log else ''}")
        if key.strip() in out:
            raise ConfigError(f"--range {key.strip()}: given twice; give each key once")
        out[key.strip()] = (lo, hi, log)
    return out


def grid_points(axes: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """Every combination of the axes' values (one empty point when there are no axes)."""
    keys = list(axes)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(axes[k] for k in keys))]


def random_points(ranges: Mapping[str, tuple[float, float, bool]], n: int, seed: int = 0) -> list[dict[str, Any]]:
    """``n`` points drawn uniformly (or log-uniformly) from the ranges, reproducibly from ``seed``."""
    rng = np.random.default_rng(seed)
    cols = {}
    for key, (lo, hi, log) in ranges.items():
        u = rng.random(n)
        cols[key] = np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))) if log else lo + u * (hi - lo)
    return [{k: float(cols[k][i]) for k in ranges} for i in range(n)]


def plan_groups(env_id: str, points: Sequence[Mapping[str, Any]]
                ) -> tuple[list[str], dict[str, KeyKind], list[dict[str, Any]], dict[tuple, list[int]]]:
    """Validate every point; group point indices by their static (shape- or code-changing) values."""
    swept = list(dict.fromkeys(k for p in points for k in p))
    kinds = {k: classify(env_id, k) for k in swept}
    checked = [{k: coerce(k, v, kinds[k].rule, where="sweep") for k, v in point.items()} for point in points]
    groups: dict[tuple, list[int]] = {}
    for i, point in enumerate(checked):
        key = tuple(sorted((k, v) for k, v in point.items() if kinds[k].static))
        groups.setdefault(key, []).append(i)
    return swept, kinds, checked, groups


@dataclasses.dataclass
class PlannedGroup:
    """One compiled group, resolved before anything compiles: its static values, its run and its rows."""

    index: int
    static: tuple
    spec: Any  # jaxrobo.training.run.RunSpec
    configs: list[int]
    meta: list[tuple[int, int, Any]]  # (config index, seed, learner params) per row
    agent_list: list[Any]
    env_list: list[Any]


@dataclasses.dataclass
class SweepPlan:
    """A validated sweep: its points, its groups and every setting its numbers depend on (``settings``)."""

    env_id: str
    swept: list[str]
    kinds: dict[str, KeyKind]
    checked: list[dict[str, Any]]
    seeds: list[int]
    groups: list[PlannedGroup]
    eval_episodes: int
    n_last: int
    max_seconds: float | None
    compiler_options: dict[str, Any] | None
    settings: dict[str, Any]


def plan_sweep(env_id: str, points: Sequence[Mapping[str, Any]], seeds: Sequence[int] = (0,),
               preset: str = "default", agent: str | None = None, overrides: Mapping[str, Any] | None = None,
               eval_episodes: int = 0, n_last: int = 100, compiler_options: dict[str, Any] | None = None,
               max_seconds: float | None = None) -> SweepPlan:
    """Validate every point and resolve every group's run (see :func:`jaxrobo.training.sweep.running.run_sweep`);
    nothing compiles.

    Raises :class:`ConfigError` naming the key for any bad key or value, in whichever group it is.
    """
    overrides = dict(overrides or {})
    overrides.setdefault("record_episodes", True)
    # A sweep compares its rows under one budget: each runs it whole (a row that stopped at its learning target
    # would still hold its slots in the group's batch), and stop_at_target is jaxrobo train's.
    if overrides.setdefault("stop_at_target", False) not in (False, "false"):
        raise ConfigError(f"stop_at_target={overrides['stop_at_target']!r}: a sweep runs every row's whole budget "
                          "to compare them; the learning-target stop is jaxrobo train's (drop it)")
    if not seeds:
        raise ConfigError("--seeds: need at least one seed")
    seeds = [int(s) for s in seeds]
    swept, kinds, checked, groups = plan_groups(env_id, points)
    options = None if compiler_options is None else dict(compiler_options)
    planned = []
    for g, (static, members) in enumerate(groups.items()):
        # The presets' on_gpu sizes are one run's: a sweep's rows share the device, its n_envs is per row.
        spec = resolve(env_id, preset, {**overrides, **dict(static)}, agent=agent, device_defaults=False)
        env, base_ap, base_ep = spec.env, spec.agent_params, spec.env.default_params
        bounds = [np.asarray(b) for b in env.state_bounds(base_ep)]
        agent_list, env_list, meta = [], [], []
        for i in members:
            point = checked[i]
            ap = base_ap.replace(**{kinds[k].name: v for k, v in point.items() if kinds[k].where == "agent"})
            ep = base_ep.replace(**{kinds[k].name: v for k, v in point.items() if kinds[k].where == "env"})
            swept_here = ", ".join(f"{k}={v!r}" for k, v in point.items())
            check_relations(ep, f"sweep point {swept_here}")  # a min above its max, refused before anything runs
            check_relations(ap, f"sweep point {swept_here}")
            given = randomise.changed(ep)
            if given and not getattr(env, "randomised", False):
                raise ConfigError(f"sweep {given[0]}={list(getattr(ep, given[0]))}: a randomisation range in a group "
                                  "with randomise=false would be ignored; set randomise=true (--set or sweep it)")
            if spec.config.discretiser != "edges" and spec.config.state_low is None:
                moved = [b for b, b0 in zip(env.state_bounds(ep), bounds) if not np.allclose(np.asarray(b), b0)]
                if moved:
                    names = [k for k in point if kinds[k].where == "env"]
                    raise ConfigError(f"sweep {', '.join(names)}: changes the discretiser's state bounds, which are "
                                      "fixed per compiled group; set state_low/state_high or sweep another key")
            for s in seeds:
                agent_list.append(ap)
                env_list.append(ep)
                meta.append((i, s, ap))
        # Every row of a group trains its own n_envs envs at once: the group's memory is that of rows x n_envs;
        # then each row's first table is evaluated, eval_episodes at once per row.
        where = f"sweep group {g + 1} ({len(meta)} rows)"
        budget.check_memory(env, spec.config.replace(n_envs=len(meta) * spec.config.n_envs),
                            Trainer(env, spec.config).disc.n_states, where=where)
        horizon = env.spec.max_episode_steps if env.spec else 1000
        budget.check_eval_memory(env, len(meta), eval_episodes, horizon, where=f"{where}: --eval-episodes")
        planned.append(PlannedGroup(g, static, spec, list(members), meta, agent_list, env_list))
    settings = {"env_id": env_id, "points": checked, "seeds": seeds, "preset": preset, "agent": agent,
                "overrides": overrides, "eval_episodes": eval_episodes, "n_last": n_last,
                "max_seconds": max_seconds, "compiler_options": options,
                "groups": [p.spec.to_dict() for p in planned]}
    return SweepPlan(env_id, swept, kinds, checked, seeds, planned, eval_episodes, n_last, max_seconds, options,
                     _canonical(settings))


def _canonical(obj: Any) -> Any:
    """``obj`` as JSON reads it back (tuples → lists, numpy scalars → Python), so saved and new settings compare."""
    return json.loads(json.dumps(obj, sort_keys=True, default=_json_default))


def _json_default(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return repr(v)
