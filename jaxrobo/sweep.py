"""Parameter sweeps as one vmapped, jitted computation: ``jaxrobo sweep``.

The seed's advice for tuning ("try several times with different parameters") becomes one command: a grid or a
random sample over learner parameters (alpha, gamma, epsilon, epsilon_discount, epsilon_min) and traced env
parameters (pos_step, limits, goals, ...), times seeds. Every (configuration, seed) row runs the whole training
loop of :class:`jaxrobo.trainer.Trainer` with its own ``n_envs`` environments and tables; the rows become a
leading axis of the parameter pytrees, and ``Trainer.init`` / ``Trainer.run_chunk`` are vmapped over it, so
the whole sweep is one compiled program (split over all devices when there are several, see
:mod:`jaxrobo.sharding`). Settings that change array shapes or code (``number_splits``, ``agent``,
``running_step``, ``control_type``, ...) cannot be vmapped: the sweep groups the rows by them and compiles one
program per distinct combination.

Row ``(config c, seed s)`` uses ``jax.random.key(s)``, exactly like ``jaxrobo train --seed s``, so every
configuration sees the same random streams (the seed's "exact same conditions") and any row can be reproduced
with a single ``jaxrobo train`` run.

    jaxrobo sweep --env CartPoleStayUp-v0 --agent qlearn --grid alpha=0.1,0.3,0.5 --grid gamma=0.9,0.99 \\
        --seeds 4 --n-envs 8 --out runs/sweep
    jaxrobo sweep --random 64 --range alpha=0.05:0.9 --range epsilon_discount=0.99:0.9999 --seeds 2

Nothing is lost: ``--out`` is checked before anything compiles (an existing file, a non-empty directory without
``--overwrite``, a parent that cannot be written are refused, exit status 2). While the sweep runs, ``--out``
holds its state: the settings and code versions (``sweep_state.json``) and the metrics of every finished group
(``checkpoint.npz``, rewritten atomically after each group). Ctrl-C or SIGTERM abandons the group in progress
(a compiled group cannot be split) and exits with 130 / 143; ``jaxrobo sweep --resume DIR`` reads the saved
settings back, skips the finished groups and writes the same ``sweep.csv`` and ``summary.json`` as an
uninterrupted sweep (timings aside). The results are written into a hidden sibling directory and replace the
state in one rename, so a directory with a ``sweep.csv`` is always a whole sweep.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import os
import shlex
import signal
import sys
import time
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.tabular import AgentParams
from jaxrobo import budget, checkpoint, driver
from jaxrobo.config import ConfigError, coerce, merge_flags, parse_overrides, parse_value
from jaxrobo.run import KeyRoute, resolve, route
from jaxrobo.struct import INT32_MAX, rules
from jaxrobo.plan import ExecutionPlan
from jaxrobo.trainer import Runner, Trainer

#: Metrics written for every row; ``final_return`` (mean return of the last 100 episodes) ranks by default.
METRICS = ("final_return", "final_length", "mean_length", "best_100_mean_length", "highest_reward",
           "episodes_done", "env_steps", "physics_nan_episodes", "eval_mean_length", "eval_mean_return")
NOT_SWEPT = ("seed",)  # the seed axis is --seeds


# ---- what a key is -------------------------------------------------------------------------------------------
#: A swept key as :func:`jaxrobo.run.route`, the router of ``--set``, places it: ``name`` (the field), ``where``
#: (``"agent"``/``"env"``: a traced learner / env parameter, vmapped; ``"train"``/``"option"``: a static loop
#: setting / env option, one compiled group per value) and ``static``.
KeyKind = KeyRoute


def classify(env_id: str, key: str) -> KeyKind:
    """Where a swept key lives: :func:`jaxrobo.run.route` (learner and loop first, as ``--set`` does;
    ``env.``/``agent.`` force a side), the seed excepted (it is the ``--seeds`` axis)."""
    if isinstance(key, str) and (key.split(".", 1)[1] if key.startswith(("env.", "agent.")) else key) in NOT_SWEPT:
        raise ConfigError(f"--grid {key}: the seed is not a swept parameter; use --seeds N (and --seed BASE)")
    return route(env_id, key, where="sweep")


# ---- which points ----------------------------------------------------------------------------------------------
def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["alpha=0.1,0.3", "gamma=0.9"]`` → ``{"alpha": [0.1, 0.3], "gamma": [0.9]}``."""
    axes: dict[str, list[Any]] = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--grid {item!r}: expected KEY=V1,V2,...")
        key, text = (s.strip() for s in item.split("=", 1))
        values = [parse_value(v.strip()) for v in text.split(",") if v.strip()]
        if not values:
            raise ConfigError(f"--grid {item!r}: no values after '='")
        axes[key] = values
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


# ---- running -------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class SweepResult:
    """One row per (configuration, seed), plus how long each compiled group took."""

    env_id: str
    swept: list[str]
    rows: list[dict[str, Any]]
    groups: list[dict[str, Any]]
    wall_seconds: float

    @property
    def env_steps(self) -> int:
        return int(sum(r["env_steps"] for r in self.rows))

    def best(self, metric: str = "final_return") -> dict[str, Any]:
        """The configuration with the highest mean of ``metric`` over its seeds."""
        by_config: dict[int, list[dict[str, Any]]] = {}
        for r in self.rows:
            by_config.setdefault(r["config"], []).append(r)
        scored = [(float(np.mean([r[metric] for r in rs])), rs) for rs in by_config.values()]
        score, rs = max(scored, key=lambda t: t[0])
        out = {k: rs[0][k] for k in self.swept}
        out.update(config=rs[0]["config"], metric=metric, mean=score,
                   std=float(np.std([r[metric] for r in rs])), seeds=len(rs))
        return out


def _as_array(values: list[Any]) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype.kind == "f":
        return arr.astype(np.float32)
    if arr.dtype.kind in "iu":
        return arr.astype(np.int32)
    return arr


def _stack(trees: list[Any]) -> Any:
    return jax.tree.map(lambda *xs: _as_array(list(xs)), *trees)


def _row_metrics(runner: Runner, n_last: int) -> dict[str, jax.Array]:
    """Per-row performance, reduced on the device (``runner`` leaves are ``[rows, n_envs, ...]``)."""
    returns = runner.returns.astype(jnp.float32)
    lengths = runner.lengths.astype(jnp.float32)
    nep = returns.shape[-1]
    k = min(n_last, nep)
    best = jnp.sort(lengths, axis=-1)[..., -min(100, nep):]
    return {
        "final_return": returns[..., -k:].mean(axis=(-1, -2)),
        "final_length": lengths[..., -k:].mean(axis=(-1, -2)),
        "mean_length": lengths.mean(axis=(-1, -2)),
        "best_100_mean_length": best.mean(axis=(-1, -2)),
        "highest_reward": returns.max(axis=(-1, -2)),
        "episodes_done": runner.episode.min(axis=-1),
        "env_steps": runner.env_steps.sum(axis=-1),
        "physics_nan_episodes": runner.nan_episodes.sum(axis=-1),
    }


class GroupRunner:
    """The compiled sweep of one static group: ``init`` / ``run_chunk`` vmapped over the row axis, compiled
    with the trainer's plan (``trainer.plan``: its compiler options, traced under it)."""

    def __init__(self, trainer: Trainer, n_rows: int, mesh: Any = None, eval_episodes: int = 0,
                 n_last: int = 100):
        from jaxrobo import sharding

        if not trainer.config.record_episodes:
            raise ValueError("a sweep needs record_episodes=True (it ranks by the last episodes' returns)")
        self.trainer, self.mesh, self.n_rows = trainer, mesh, n_rows
        self.n_padded = sharding.padded_size(n_rows, mesh)
        self.eval_episodes, self.n_last = eval_episodes, n_last
        self.compile_seconds = self.run_seconds = 0.0
        self.complete = False

    def _init(self, key_data, agent_params, env_params):
        keys = jax.random.wrap_key_data(key_data)
        return jax.vmap(self.trainer.init)(keys, agent_params, env_params)

    def _chunk(self, runner, agent_params, env_params):
        return jax.vmap(self.trainer.run_chunk)(runner, agent_params, env_params)

    def _finish(self, runner, key_data, env_params):
        out = _row_metrics(runner, self.n_last)
        if self.eval_episodes > 0:
            shared = self.trainer.config.shared_table
            table = runner.agent if shared else jax.tree.map(lambda x: x[:, 0], runner.agent)
            keys = jax.vmap(lambda kd: jax.random.fold_in(jax.random.wrap_key_data(kd), 1))(key_data)
            ev = jax.vmap(self.trainer.evaluate, in_axes=(0, 0, None, 0))
            ret, length = ev(keys, table, self.eval_episodes, env_params)
            out["eval_mean_return"] = ret.mean(axis=-1)
            out["eval_mean_length"] = length.astype(jnp.float32).mean(axis=-1)
        return out

    def run(self, key_data: np.ndarray, agent_params: Any, env_params: Any,
            progress: Callable[[int, int], None] | None = None,
            max_seconds: float | None = None, stop: Callable[[], bool] | None = None) -> dict[str, np.ndarray]:
        """Train every row to its last episode (or until ``max_seconds`` of running); per-row metrics as host
        arrays of length ``n_rows``. ``self.complete`` says whether every row finished. The chunk loop is the
        host driver's (:func:`jaxrobo.driver.run_chunks`): ``stop`` is polled before every chunk; when it returns
        True the group is abandoned with :class:`SweepInterrupted`."""
        from jaxrobo import sharding

        mesh, n = self.mesh, self.n_padded
        host = sharding.pad_rows((key_data, agent_params, env_params), n)
        kd, ap, ep = sharding.put_batch(host, mesh)
        t0 = time.perf_counter()
        plan = self.trainer.plan
        opts = plan.xla_options
        init = sharding.jit_batched(self._init, mesh, n, (kd, ap, ep), compiler_options=opts)
        runner = driver.compile_under(plan, init, kd, ap, ep)(kd, ap, ep)
        chunk = sharding.jit_batched(self._chunk, mesh, n, (runner, ap, ep), donate=(0,), compiler_options=opts)
        chunk = driver.compile_under(plan, chunk, runner, ap, ep)
        finish = sharding.jit_batched(self._finish, mesh, n, (runner, kd, ep), compiler_options=opts)
        finish = driver.compile_under(plan, finish, runner, kd, ep)
        stats = driver.compiled_progress(runner)
        jax.block_until_ready(runner)
        self.compile_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        nepisodes = self.trainer.config.nepisodes
        report = None if progress is None else (lambda done, total, _last: progress(done, total))
        loop = driver.run_chunks(lambda r: chunk(r, ap, ep), runner, self.trainer.max_chunks(), read=stats,
                                 total=nepisodes, progress=report, should_stop=stop, max_seconds=max_seconds)
        if loop.stopped:
            raise SweepInterrupted(0, 1, None)
        self.complete = loop.done >= nepisodes
        out = finish(loop.carry, kd, ep)
        out = sharding.gather(out)
        self.run_seconds = time.perf_counter() - t0
        return {k: np.asarray(v)[: self.n_rows] for k, v in out.items()}


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
    spec: Any  # jaxrobo.run.RunSpec
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
    """Validate every point and resolve every group's run (see :func:`run_sweep`); nothing compiles.

    Raises :class:`ConfigError` naming the key for any bad key or value, in whichever group it is.
    """
    overrides = dict(overrides or {})
    overrides.setdefault("record_episodes", True)
    if not seeds:
        raise ConfigError("--seeds: need at least one seed")
    seeds = [int(s) for s in seeds]
    swept, kinds, checked, groups = plan_groups(env_id, points)
    options = None if compiler_options is None else dict(compiler_options)
    planned = []
    for g, (static, members) in enumerate(groups.items()):
        spec = resolve(env_id, preset, {**overrides, **dict(static)}, agent=agent)
        env, base_ap, base_ep = spec.env, spec.agent_params, spec.env.default_params
        bounds = [np.asarray(b) for b in env.state_bounds(base_ep)]
        agent_list, env_list, meta = [], [], []
        for i in members:
            point = checked[i]
            ap = base_ap.replace(**{kinds[k].name: v for k, v in point.items() if kinds[k].where == "agent"})
            ep = base_ep.replace(**{kinds[k].name: v for k, v in point.items() if kinds[k].where == "env"})
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
        # Every row of a group trains its own n_envs envs at once: the group's memory is that of rows x n_envs.
        budget.check_memory(env, spec.config.replace(n_envs=len(meta) * spec.config.n_envs),
                            Trainer(env, spec.config).disc.n_states, where=f"sweep group {g + 1} ({len(meta)} rows)")
        planned.append(PlannedGroup(g, static, spec, list(members), meta, agent_list, env_list))
    settings = {"env_id": env_id, "points": checked, "seeds": seeds, "preset": preset, "agent": agent,
                "overrides": overrides, "eval_episodes": eval_episodes, "n_last": n_last,
                "max_seconds": max_seconds, "compiler_options": options,
                "groups": [p.spec.to_dict() for p in planned]}
    return SweepPlan(env_id, swept, kinds, checked, seeds, planned, eval_episodes, n_last, max_seconds, options,
                     _canonical(settings))


def run_sweep(env_id: str, points: Sequence[Mapping[str, Any]], seeds: Sequence[int] = (0,),
              preset: str = "default", agent: str | None = None, overrides: Mapping[str, Any] | None = None,
              mesh: Any = None, eval_episodes: int = 0, n_last: int = 100,
              log: Callable[[str], None] | None = None,
              progress: Callable[[int, int], None] | None = None,
              compiler_options: dict[str, Any] | None = None, max_seconds: float | None = None,
              state_dir: str | None = None, should_stop: Callable[[], bool] | None = None) -> SweepResult:
    """Train every point × seed; rows grouped by static settings, one compiled program per group.

    ``points`` map swept keys to values (see :func:`classify`); ``overrides`` apply to every point (like
    ``--set``); ``max_seconds`` stops each group's training early (its rows then have ``episodes_done`` below
    ``nepisodes`` and the group ``complete: False``). Raises :class:`ConfigError` naming the key for any bad
    key or value, before compiling. ``state_dir`` and ``should_stop`` make it resumable: see :func:`run_plan`.
    """
    plan = plan_sweep(env_id, points, seeds, preset, agent, overrides, eval_episodes, n_last, compiler_options,
                      max_seconds)
    return run_plan(plan, mesh, log, progress, state_dir, should_stop)


def run_plan(plan: SweepPlan, mesh: Any = None, log: Callable[[str], None] | None = None,
             progress: Callable[[int, int], None] | None = None, state_dir: str | None = None,
             should_stop: Callable[[], bool] | None = None, state_extra: Mapping[str, Any] | None = None
             ) -> SweepResult:
    """Run a planned sweep, group by group.

    ``state_dir`` makes the sweep resumable by finished groups: the sweep's settings, the code's versions and
    their fingerprint go to ``state_dir/sweep_state.json`` before the first compile (with ``state_extra``, kept
    but not compared), and the row metrics of every finished group to ``state_dir/checkpoint.npz`` (rewritten
    atomically after each group; an empty one at the start). Running the same plan again on the same
    ``state_dir`` skips the saved groups and gives the same rows; a state saved by other settings or other code
    raises :class:`ConfigError` before anything compiles. ``should_stop`` is polled before each group and before
    each training chunk; when it returns True the sweep abandons the group it is in (a compiled group cannot be
    split) and raises :class:`SweepInterrupted`, the finished groups staying saved. With several processes only
    process 0 writes; the others read ``state_dir`` if they are given it (a shared file system).
    """
    log = log or (lambda _msg: None)
    planned = plan.groups
    saved: dict[int, dict[str, Any]] = {}
    fingerprint = None
    if state_dir is not None:
        state = open_state(state_dir, plan, state_extra)
        fingerprint = state["fingerprint"]
        saved = load_checkpoint(state_dir, plan, fingerprint)
        if saved:
            log(f"resuming: {len(saved)} of {len(planned)} groups already finished in {state_dir}")
        elif jax.process_index() == 0:
            save_checkpoint(state_dir, fingerprint, plan, saved)

    rows: list[dict[str, Any]] = []
    timings: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for p in planned:
        g, static, spec, meta = p.index, p.static, p.spec, p.meta
        label = ", ".join(f"{k}={v}" for k, v in static) or "all"
        if g in saved:
            log(f"group {g + 1}/{len(planned)} [{label}]: finished before, read from {state_dir}")
        else:
            if should_stop is not None and should_stop():
                raise SweepInterrupted(len(saved), len(planned), state_dir)
            key_data = np.stack([np.asarray(jax.random.key_data(jax.random.key(s))) for (_, s, _) in meta])
            execution = ExecutionPlan.for_run(spec.env, spec.config, compiler_options=plan.compiler_options)
            trainer = Trainer(spec.env, spec.config, plan=execution)
            group = GroupRunner(trainer, len(meta), mesh, plan.eval_episodes, plan.n_last)
            log(f"group {g + 1}/{len(planned)} [{label}]: {len(p.configs)} configs × {len(plan.seeds)} seeds × "
                f"{spec.config.n_envs} envs, {spec.config.nepisodes} episodes ≤ {spec.config.nsteps} steps")
            try:
                metrics = group.run(key_data, _stack(p.agent_list), _stack(p.env_list), progress, plan.max_seconds,
                                    stop=should_stop)
            except SweepInterrupted:
                raise SweepInterrupted(len(saved), len(planned), state_dir) from None
            saved[g] = {"metrics": metrics, "compile_seconds": group.compile_seconds,
                        "run_seconds": group.run_seconds, "complete": group.complete}
            if state_dir is not None and jax.process_index() == 0:
                save_checkpoint(state_dir, fingerprint, plan, saved)
        done = saved[g]
        metrics = done["metrics"]
        steps = int(metrics["env_steps"].astype(np.int64).sum())
        timings.append({"group": g, "static": dict(static), "rows": len(meta), "n_envs": spec.config.n_envs,
                        "compile_seconds": done["compile_seconds"], "run_seconds": done["run_seconds"],
                        "env_steps": steps, "env_steps_per_second": steps / max(done["run_seconds"], 1e-9),
                        "complete": done["complete"]})
        log(f"  compiled in {done['compile_seconds']:.1f} s; {steps:,} env steps in {done['run_seconds']:.1f} s "
            f"({steps / max(done['run_seconds'], 1e-9):,.0f} steps/s)")
        for r, (i, s, ap) in enumerate(meta):
            row: dict[str, Any] = {"config": i, "seed": s, "group": g}
            row.update(plan.checked[i])
            row.update({k: float(getattr(ap, k)) for k in rules(AgentParams)})
            for m, values in metrics.items():
                v = values[r]
                row[m] = int(v) if np.issubdtype(values.dtype, np.integer) else float(v)
            rows.append(row)
    rows.sort(key=lambda r: (r["config"], r["seed"]))
    return SweepResult(plan.env_id, plan.swept, rows, timings, time.perf_counter() - t_all)


# ---- saved progress: finished groups survive an interrupt or a crash ----------------------------------------
STATE_FILE = "sweep_state.json"
STATE_FORMAT = 1


class SweepInterrupted(Exception):
    """The sweep's stop hook fired; ``done`` of ``total`` groups are finished (and saved in ``state_dir``)."""

    def __init__(self, done: int, total: int, state_dir: str | None):
        super().__init__(f"interrupted with {done} of {total} groups finished")
        self.done, self.total, self.state_dir = done, total, state_dir


def code_version() -> dict[str, str]:
    """What the sweep's numbers depend on besides its settings: jaxrobo's sources and the libraries' versions."""
    from importlib import metadata

    import jaxrobo
    from jaxrobo.rundir import source_hash

    out = {"jaxrobo": jaxrobo.__version__, "jaxrobo_sources": source_hash()}
    for dist in ("jax", "jaxlib", "numpy", "mujoco", "mujoco-mjx", "brax"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    return out


def _canonical(obj: Any) -> Any:
    """``obj`` as JSON reads it back (tuples → lists, numpy scalars → Python), so saved and new settings compare."""
    return json.loads(json.dumps(obj, sort_keys=True, default=_json_default))


def _json_default(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return repr(v)


def read_state(state_dir: str) -> dict[str, Any]:
    """The saved ``sweep_state.json`` of ``state_dir``: settings, versions, fingerprint and extra."""
    path = os.path.join(state_dir, STATE_FILE)
    try:
        with open(path) as f:
            state = json.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{state_dir}: not a sweep ({STATE_FILE} missing)") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: unreadable sweep state ({err})") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        raise ConfigError(f"{path}: not a sweep state this jaxrobo reads (format {found!r}, expected {STATE_FORMAT})")
    return state


def open_state(state_dir: str, plan: SweepPlan, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The saved state of ``plan`` in ``state_dir``: checked to be this sweep's (same settings and code) if there
    is one, else written (process 0). Raises :class:`ConfigError` saying what differs."""
    import hashlib

    from jaxrobo import rundir

    versions = code_version()
    fingerprint = hashlib.sha256(json.dumps([plan.settings, versions], sort_keys=True).encode()).hexdigest()
    if os.path.exists(os.path.join(state_dir, STATE_FILE)):
        state = read_state(state_dir)
        if state.get("fingerprint") != fingerprint:
            old_v, old_s = state.get("versions", {}), state.get("settings", {})
            code = [k if k == "jaxrobo_sources" else f"{k} {old_v.get(k)} → {versions[k]}"
                    for k in versions if old_v.get(k) != versions[k]]
            diff = sorted(k for k in set(plan.settings) | set(old_s) if plan.settings.get(k) != old_s.get(k))
            why = (f"by other code ({', '.join(code)} changed)" if code else
                   f"by a sweep with other settings ({', '.join(diff) or 'fingerprint'} differ)")
            raise ConfigError(f"{state_dir}: cannot resume: its sweep state was saved {why}; "
                              "start it again with --overwrite, or sweep into another --out")
        return state
    state = {"format": STATE_FORMAT, "fingerprint": fingerprint, "versions": versions, "settings": plan.settings,
             "extra": _canonical(dict(extra or {}))}
    if jax.process_index() == 0:
        rundir.atomic_write_json(os.path.join(state_dir, STATE_FILE), state)
    return state


def save_checkpoint(state_dir: str, fingerprint: str, plan: SweepPlan, finished: Mapping[int, Mapping[str, Any]]
                    ) -> None:
    """The row metrics of every finished group in ``state_dir/checkpoint.npz`` (plain arrays, no pickle),
    written atomically (:func:`jaxrobo.checkpoint.write_npz`): a crash leaves the previous checkpoint or this one."""
    from jaxrobo import rundir

    arrays: dict[str, np.ndarray] = {"fingerprint": np.asarray(fingerprint),
                                     "finished": np.asarray(sorted(finished), np.int64)}
    for g, done in finished.items():
        p = plan.groups[g]
        arrays[f"g{g}_config"] = np.asarray([i for i, _, _ in p.meta], np.int64)
        arrays[f"g{g}_seed"] = np.asarray([s for _, s, _ in p.meta], np.int64)
        for k in ("compile_seconds", "run_seconds"):
            arrays[f"g{g}_{k}"] = np.asarray(done[k], np.float64)
        arrays[f"g{g}_complete"] = np.asarray(bool(done["complete"]))
        arrays.update({f"g{g}_metric_{k}": np.asarray(v) for k, v in done["metrics"].items()})
    checkpoint.write_npz(os.path.join(state_dir, rundir.CHECKPOINT), **arrays)


def load_checkpoint(state_dir: str, plan: SweepPlan, fingerprint: str) -> dict[int, dict[str, Any]]:
    """The finished groups saved in ``state_dir``: ``{group: {"metrics", "compile_seconds", "run_seconds",
    "complete"}}`` (empty without a checkpoint). Raises :class:`ConfigError` for one of another sweep."""
    from jaxrobo import rundir

    path = os.path.join(state_dir, rundir.CHECKPOINT)
    if not os.path.exists(path):
        return {}
    data = checkpoint.read_npz(path, "the sweep checkpoint")
    if str(data.get("fingerprint")) != fingerprint:
        raise ConfigError(f"{path}: saved by another sweep than {os.path.join(state_dir, STATE_FILE)}; "
                          "start it again with --overwrite")
    out = {}
    for g in (int(x) for x in data["finished"]):
        p = plan.groups[g]
        if not (np.array_equal(data[f"g{g}_config"], [i for i, _, _ in p.meta])
                and np.array_equal(data[f"g{g}_seed"], [s for _, s, _ in p.meta])):
            raise ConfigError(f"{path}: group {g} holds other rows than the sweep plans")
        prefix = f"g{g}_metric_"
        out[g] = {"metrics": {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)},
                  "compile_seconds": float(data[f"g{g}_compile_seconds"]),
                  "run_seconds": float(data[f"g{g}_run_seconds"]), "complete": bool(data[f"g{g}_complete"])}
    return out


# ---- output --------------------------------------------------------------------------------------------------
def write_csv(result: SweepResult, path: str) -> None:
    keys = list(dict.fromkeys(k for r in result.rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(result.rows)


def plot_sweep(result: SweepResult, out_dir: str, metric: str = "final_return") -> list[str]:
    """Heatmaps of the mean ``metric`` over each pair of swept keys (scatter for sampled values); PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.rows
    numeric = [k for k in result.swept if all(isinstance(r[k], (int, float)) and not isinstance(r[k], bool)
                                               for r in rows)]
    keys = [k for k in result.swept if len({r[k] for r in rows}) > 1]
    paths = []
    if len(keys) == 1:
        k = keys[0]
        xs = sorted({r[k] for r in rows}, key=_sort_key)
        means = [np.mean([r[metric] for r in rows if r[k] == x]) for x in xs]
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.scatter([str(r[k]) if k not in numeric else r[k] for r in rows], [r[metric] for r in rows], s=10,
                   alpha=0.4, label="one seed")
        ax.plot([str(x) if k not in numeric else x for x in xs], means, "o-", color="C1", label="mean over seeds")
        ax.set_xlabel(k)
        ax.set_ylabel(metric)
        ax.legend()
        paths.append(_save(fig, out_dir, f"sweep_{k}.png"))
    for a, b in itertools.combinations(keys, 2):
        xa = sorted({r[a] for r in rows}, key=_sort_key)
        xb = sorted({r[b] for r in rows}, key=_sort_key)
        fig, ax = plt.subplots(figsize=(1.2 + 0.8 * max(len(xa), 3), 1.2 + 0.6 * max(len(xb), 3)))
        pairs = {(r[a], r[b]) for r in rows}
        if len(pairs) == len(xa) * len(xb) <= 400:  # every combination present: a grid
            grid = np.full((len(xb), len(xa)), np.nan)
            for i, vb in enumerate(xb):
                for j, va in enumerate(xa):
                    vals = [r[metric] for r in rows if r[a] == va and r[b] == vb]
                    if vals:
                        grid[i, j] = np.mean(vals)
            im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
            ax.set_xticks(range(len(xa)), [_fmt(v) for v in xa], rotation=45)
            ax.set_yticks(range(len(xb)), [_fmt(v) for v in xb])
            if grid.size <= 100:
                for i in range(len(xb)):
                    for j in range(len(xa)):
                        if np.isfinite(grid[i, j]):
                            ax.text(j, i, f"{grid[i, j]:.0f}", ha="center", va="center", color="w", fontsize=8)
        else:  # sampled values: one dot per row
            im = ax.scatter([r[a] for r in rows], [r[b] for r in rows], c=[r[metric] for r in rows], cmap="viridis")
        fig.colorbar(im, ax=ax, label=f"{metric} (mean over seeds)")
        ax.set_xlabel(a)
        ax.set_ylabel(b)
        ax.set_title(f"{result.env_id}: {metric}", fontsize=9)
        paths.append(_save(fig, out_dir, f"heatmap_{a}_{b}.png"))
    return paths


def _sort_key(v: Any) -> tuple:
    return (0, v, "") if isinstance(v, (int, float)) else (1, 0, str(v))


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _save(fig: Any, out_dir: str, name: str) -> str:
    import matplotlib.pyplot as plt

    path = os.path.join(out_dir, name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ---- command line ----------------------------------------------------------------------------------------------
#: The flags that define a sweep, with their defaults: saved with its state and read back by ``--resume``.
SWEEP_FLAGS: dict[str, Any] = {"env": "CartPoleStayUp-v0", "agent": None, "preset": "default", "grid": None,
                               "random": 0, "ranges": None, "seeds": 4, "seed": 0, "n_envs": None, "nepisodes": None,
                               "nsteps": None, "set": None, "eval_episodes": 10, "metric": "final_return",
                               "no_plots": False}
_FLAG_NAMES = {"ranges": "--range", "n_envs": "--n-envs", "eval_episodes": "--eval-episodes",
               "no_plots": "--no-plots"}


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``jaxrobo sweep``. The sweep-defining flags parse to None when absent (defaults in
    :data:`SWEEP_FLAGS`), so ``--resume`` can tell a flag given again from one left out."""
    d = SWEEP_FLAGS
    parser.add_argument("--env", default=None, help=f"environment id (see `jaxrobo list`; default {d['env']})")
    parser.add_argument("--agent", default=None, help="qlearn | sarsa | expected_sarsa | double_q")
    parser.add_argument("--preset", default=None, help="parameter preset of the env's agent YAML (default default)")
    parser.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                        help="values of one swept key (repeatable; the grid is their product)")
    parser.add_argument("--random", type=int, default=None, metavar="N", help="N random points from the --range's")
    parser.add_argument("--range", action="append", metavar="KEY=LOW:HIGH[:log]", dest="ranges",
                        help="sampling range of one key for --random (repeatable)")
    parser.add_argument("--seeds", type=int, default=None,
                        help=f"seeds per configuration (rows = configs × seeds; default {d['seeds']})")
    parser.add_argument("--seed", type=int, default=None, help="first seed; seeds are SEED .. SEED+N-1 (default 0)")
    parser.add_argument("--n-envs", type=int, default=None, help="environments (tables) per row")
    parser.add_argument("--nepisodes", type=int, default=None, help="episodes per environment")
    parser.add_argument("--nsteps", type=int, default=None, help="step cap per episode")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="fixed override for every row")
    parser.add_argument("--eval-episodes", type=int, default=None,
                        help=f"greedy evaluation episodes of each row's first table (0: none; default "
                             f"{d['eval_episodes']})")
    parser.add_argument("--metric", default=None, choices=METRICS,
                        help=f"what ranks configurations (default {d['metric']})")
    parser.add_argument("--shard", choices=("auto", "on", "off"), default="auto",
                        help="split rows over all devices (auto: when there is more than one)")
    parser.add_argument("--out", default=None, help="output directory (default sweep_results/<env>_<time>); "
                        "must be new or empty unless --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="replace the jaxrobo run or sweep in --out")
    parser.add_argument("--resume", default=None, metavar="DIR",
                        help="go on with the interrupted sweep in DIR: its saved settings, its unfinished groups")
    parser.add_argument("--no-plots", action="store_true", default=None, help="skip the heatmap PNGs")


def _flag(dest: str) -> str:
    return _FLAG_NAMES.get(dest, "--" + dest)


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return "(given)" if value else "(not given)"
    return " ".join(map(str, value)) if isinstance(value, list) else str(value)


def sweep_flags(args: argparse.Namespace, check_out: bool = True) -> tuple[str, dict[str, Any], list[str]]:
    """The output directory, the sweep-defining flags and the command line of the sweep, checked at the boundary.

    A new sweep: ``--out`` must be new or empty (or a run, with ``--overwrite``); ``check_out=False`` skips that
    check (processes other than 0, which never write it). ``--resume DIR``: DIR must hold an interrupted sweep,
    whose saved flags are used (a flag given again must say the same) and whose ``status.json`` names the output
    directory (DIR itself, or the run an ``--overwrite`` sweep replaces). Raises :class:`ConfigError` naming the
    flag."""
    from jaxrobo import rundir
    from jaxrobo.registry import find

    given = {k: getattr(args, k, None) for k in SWEEP_FLAGS}
    if args.resume is None:
        env_id = given["env"] or SWEEP_FLAGS["env"]
        find(env_id, where=f"--env {env_id}")  # imports the module of a 'module:Id'; a missing one names --env
        out = args.out or os.path.join("sweep_results", f"{env_id.rpartition(':')[2]}_"
                                                        f"{time.strftime('%Y%m%d-%H%M%S')}")
        if check_out:
            rundir.check_out(out, overwrite=args.overwrite)
        flags = {k: SWEEP_FLAGS[k] if v is None else v for k, v in given.items()}
        return out, flags, list(sys.argv)
    live = args.resume
    if args.overwrite:
        raise ConfigError(f"--resume {live}: cannot be combined with --overwrite (one continues the sweep, the "
                          "other replaces it)")
    if args.out is not None:
        raise ConfigError(f"--out {args.out}: a resumed sweep finishes where it was going to; drop --out")
    rundir.check_out(live, resume=True, flag="--resume")
    extra = read_state(live).get("extra", {})
    saved = extra.get("flags")
    if not isinstance(saved, dict) or set(saved) != set(SWEEP_FLAGS):
        raise ConfigError(f"--resume {live}: its sweep state has no command-line flags to resume from")
    for k, v in given.items():
        if v is not None and _canonical(v) != saved[k]:
            raise ConfigError(f"--resume {live}: {_flag(k)} {_show(v)} differs from the saved sweep's "
                              f"{_flag(k)} {_show(saved[k])}; a resumed sweep keeps its settings (drop the flag)")
    find(saved["env"], where=f"--resume {live}: env {saved['env']}")  # a 'module:Id' imports its module again
    out = (rundir.read_status(live) or {}).get("out") or live
    return out, dict(saved), list(extra.get("argv") or [])


def _all_agree(ok: bool) -> bool:
    """Whether every process accepted the sweep: with several, all of them run it or none does (one alone
    would wait forever for the others)."""
    if jax.process_count() == 1:
        return ok
    from jax.experimental import multihost_utils

    return bool(np.all(multihost_utils.process_allgather(np.asarray(ok))))


def points_from_args(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The grid (product of --grid axes) times the --random sample (if any)."""
    axes = parse_grid(args.grid or [])
    ranges = parse_ranges(args.ranges or [])
    for key, values in list(axes.items()):  # "--grid alpha=0.05:0.9" with --random is a range
        if len(values) == 1 and isinstance(values[0], str) and ":" in values[0] and args.random:
            ranges.update(parse_ranges([f"{key}={values[0]}"]))
            del axes[key]
    if ranges and not args.random:
        raise ConfigError("--range needs --random N (how many points to draw)")
    if args.random and not ranges:
        raise ConfigError("--random N needs at least one --range KEY=LOW:HIGH")
    if args.random < 0:
        raise ConfigError(f"--random {args.random}: must be >= 0")
    grid = grid_points(axes)
    if not args.random:
        return grid
    sample = random_points(ranges, args.random, args.seed)
    return [{**g, **s} for g in grid for s in sample]


def run(args: argparse.Namespace, *, compiler_options: Mapping[str, Any] | None = None) -> int:
    """``jaxrobo sweep`` (see :func:`_run`); Ctrl-C before the sweep's own handlers are in place exits with 130
    and one line (nothing is half-written: the state and the results are written atomically).
    ``compiler_options``: XLA options for every group's plan (part of the sweep's saved settings)."""
    try:
        return _run(args, compiler_options)
    except KeyboardInterrupt:
        print("jaxrobo sweep: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT


def _run(args: argparse.Namespace, compiler_options: Mapping[str, Any] | None = None) -> int:
    """``jaxrobo sweep``: train every row, write sweep.csv, summary.json and heatmaps, print the best.

    The sweep's state (``status.json``, ``sweep_state.json``, ``checkpoint.npz`` with the finished groups) lives
    in the output directory while it runs, or, with ``--overwrite``, in a hidden sibling, so that the old run
    stays whole until the new one replaces it. The results are written into a hidden sibling and replace the
    state (or the old run) in one rename. SIGINT / SIGTERM stop the sweep with exit status 130 / 143, the
    finished groups saved for ``--resume``."""
    from jaxrobo import rundir, sharding

    error = None
    try:
        sharding.initialize_distributed()  # a no-op unless JAXROBO_COORDINATOR & co. are set (docs/scaling.md)
        main_process = jax.process_index() == 0
        out, flags, argv = sweep_flags(args, check_out=main_process)
        live = args.resume  # where the state is; a new sweep's is chosen by process 0 below
        f = argparse.Namespace(**flags)
        if f.seeds < 1:
            raise ConfigError(f"--seeds {f.seeds}: must be >= 1")
        if f.eval_episodes < 0:
            raise ConfigError(f"--eval-episodes {f.eval_episodes}: must be >= 0")
        if f.metric.startswith("eval_") and f.eval_episodes == 0:
            raise ConfigError(f"--metric {f.metric}: needs --eval-episodes > 0")
        points = points_from_args(f)
        overrides = merge_flags(parse_overrides(f.set or []), [("n_envs", "--n-envs", f.n_envs),
                                                                ("nepisodes", "--nepisodes", f.nepisodes),
                                                                ("nsteps", "--nsteps", f.nsteps)])
        if f.seed < 0 or f.seed + f.seeds - 1 > INT32_MAX:
            raise ConfigError(f"--seed {f.seed} --seeds {f.seeds}: the seeds run from --seed to --seed + --seeds - 1, "
                              f"which must lie in [0, {INT32_MAX}]")
        seeds = list(range(f.seed, f.seed + f.seeds))
        plan = plan_sweep(f.env, points, seeds, f.preset, f.agent, overrides, f.eval_episodes,
                          compiler_options=compiler_options)
        if args.resume is not None:
            open_state(live, plan)  # refuses a state of other settings or code before anything compiles
        mesh = None
        if args.shard == "on" or (args.shard == "auto" and jax.device_count() > 1):
            mesh = sharding.make_mesh()
    except (ConfigError, ValueError) as err:
        error = str(err)
    if not _all_agree(error is None):
        print(f"jaxrobo sweep: {error or 'another process refused the sweep (see its output)'}", file=sys.stderr)
        return 2
    if main_process and live is None:
        # The state of a new sweep goes to --out itself (new or empty), so that a hard crash leaves it resumable;
        # with --overwrite (checked above) to a hidden sibling, so that the old run stays whole until the end.
        live = rundir.live_dir(out)
    resume_hint = (f"jaxrobo sweep --resume {shlex.quote(live)}" if live is not None
                   else "jaxrobo sweep --resume DIR (DIR as process 0 says)")
    if main_process:
        rundir.write_status(live, rundir.RUNNING, command="sweep", out=os.path.abspath(out), resume=resume_hint)
    print(f"{f.env}: {len(points)} configurations × {len(seeds)} seeds in {len(plan.groups)} groups"
          f"{f' over {mesh.devices.size} devices' if mesh is not None else ''} → {out}")
    if live is not None and os.path.abspath(live) != os.path.abspath(out):
        print(f"state in {live} until the sweep is done", file=sys.stderr)
    # Other processes read the state only when resuming (a new sweep's state directory is process 0's choice).
    state_dir = live
    owned = live if main_process else None  # the directory whose status this process writes
    with driver.StopOnSignal() as stop:
        # Processes stop together (a signal may reach only some of them): one more collective per chunk.
        should_stop = stop if jax.process_count() == 1 else (lambda: not _all_agree(not stop()))
        saved_in = live or "process 0"
        try:
            result = run_plan(plan, mesh, log=print, state_dir=state_dir, should_stop=should_stop,
                              state_extra={"flags": flags, "argv": argv})
        except KeyboardInterrupt:  # a second Ctrl-C: the group in progress is dropped at once
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               what=f"interrupted by SIGINT: the finished groups are saved in {saved_in}")
            return 128 + signal.SIGINT
        except SweepInterrupted as err:
            name = stop.name or "a signal to another process"
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               finished_groups=err.done, groups=err.total,
                               what=f"interrupted by {name}: {err.done} of {err.total} groups finished, saved in "
                                    f"{saved_in}")
            return 128 + (stop.signum or signal.SIGINT)
        except Exception as err:  # the finished groups are saved: say how to go on, then fail as before
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               error=f"{type(err).__name__}: {err}",
                               what=f"failed ({type(err).__name__}); the finished groups are saved in {saved_in}")
            raise
    if not main_process:
        return 0
    metric = f.metric
    best = result.best(metric)
    summary = {"env_id": f.env, "agent": f.agent, "preset": f.preset, "swept": result.swept,
               "seeds": seeds, "n_rows": len(result.rows), "wall_seconds": result.wall_seconds,
               "env_steps": result.env_steps, "env_steps_per_second": result.env_steps / max(result.wall_seconds, 1e-9),
               "groups": result.groups, "best": best, "argv": argv}
    plots: list[str] = []

    def write(staged: str) -> None:
        write_csv(result, os.path.join(staged, "sweep.csv"))
        with open(os.path.join(staged, "summary.json"), "w") as fh:
            json.dump(summary, fh, indent=2, default=str)
        plots.extend([] if f.no_plots else plot_sweep(result, staged, metric))
        rundir.write_status(staged, rundir.COMPLETE, command="sweep")

    rundir.publish_results(out, live, write)  # replaces the state (or the old run) in one step
    plots = [os.path.join(out, os.path.basename(p)) for p in plots]
    print(f"{len(result.rows)} rows, {result.env_steps:,} env steps in {result.wall_seconds:.1f} s "
          f"({summary['env_steps_per_second']:,.0f} steps/s incl. compile)")
    print("best configuration: " + ", ".join(f"{k}={_fmt(best[k])}" for k in result.swept) +
          f"  ({metric} {best['mean']:.1f} ± {best['std']:.1f} over {best['seeds']} seeds)")
    print(f"results: {os.path.join(out, 'sweep.csv')}" + (f"; plots: {', '.join(plots)}" if plots else ""))
    return 0


def main(argv: Sequence[str] | None = None, *, compiler_options: Mapping[str, Any] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxrobo sweep", description=__doc__.split("\n\n")[0])
    configure_parser(parser)
    return run(parser.parse_args(argv), compiler_options=compiler_options)


if __name__ == "__main__":
    sys.exit(main())
