"""Parameter sweeps as one vmapped, jitted computation: ``jaxrobo sweep``.

The seed's advice for tuning ("try several times with different parameters") becomes one command: a grid or a
random sample over learner parameters (alpha, gamma, epsilon, epsilon_discount, epsilon_min) and traced env
parameters (pos_step, limits, goals, ...), times seeds. Every (configuration, seed) row runs the whole training
loop of :class:`jaxrobo.train.Trainer` with its own ``n_envs`` environments and tables; the rows become a
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
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import os
import sys
import time
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from agents.tabular import AgentParams
from jaxrobo.config import ConfigError, coerce, parse_overrides, parse_value, unknown_key
from jaxrobo.registry import _lookup
from jaxrobo.struct import rules
from jaxrobo.train import Runner, TrainConfig, Trainer

#: Metrics written for every row; ``final_return`` (mean return of the last 100 episodes) ranks by default.
METRICS = ("final_return", "final_length", "mean_length", "best_100_mean_length", "highest_reward",
           "episodes_done", "env_steps", "physics_nan_episodes", "eval_mean_length", "eval_mean_return")
NOT_SWEPT = ("seed",)  # the seed axis is --seeds
#: XLA options for the sweep's compiles (tests lower the optimisation level to compile faster).
COMPILER_OPTIONS: dict[str, Any] | None = None


# ---- what a key is -------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class KeyKind:
    name: str
    where: str  # "agent" (traced learner param), "env" (traced env param), "train" / "option" (static)
    rule: Any

    @property
    def static(self) -> bool:
        return self.where in ("train", "option")


def classify(env_id: str, key: str) -> KeyKind:
    """Where a swept key lives (learner and loop first, as ``--set`` does; ``env.``/``agent.`` force a side)."""
    env_cls = _lookup(env_id).env_class()
    agent, train = rules(AgentParams), rules(TrainConfig)
    opts, params = rules(env_cls.Options), rules(env_cls.Params)
    forced = None
    if key.startswith(("env.", "agent.")):
        forced, key = key.split(".", 1)
    if key in NOT_SWEPT:
        raise ConfigError(f"--grid {key}: the seed is not a swept parameter; use --seeds N (and --seed BASE)")
    tables = []
    if forced in (None, "agent"):
        tables += [("agent", agent), ("train", train)]
    if forced in (None, "env"):
        tables += [("option", opts), ("env", params)]
    for where, table in tables:
        if key in table:
            return KeyKind(key, where, table[key])
    raise unknown_key(key, set(agent) | set(train) | set(opts) | set(params), where="sweep")


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
    """The compiled sweep of one static group: ``init`` / ``run_chunk`` vmapped over the row axis."""

    def __init__(self, trainer: Trainer, n_rows: int, mesh: Any = None, eval_episodes: int = 0,
                 n_last: int = 100, compiler_options: dict[str, Any] | None = None):
        from jaxrobo import sharding

        if not trainer.config.record_episodes:
            raise ValueError("a sweep needs record_episodes=True (it ranks by the last episodes' returns)")
        self.trainer, self.mesh, self.n_rows = trainer, mesh, n_rows
        self.n_padded = sharding.padded_size(n_rows, mesh)
        self.eval_episodes, self.n_last = eval_episodes, n_last
        self.compile_seconds = self.run_seconds = 0.0
        self.complete = False
        self.options = COMPILER_OPTIONS if compiler_options is None else compiler_options

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
            max_seconds: float | None = None) -> dict[str, np.ndarray]:
        """Train every row to its last episode (or until ``max_seconds`` of running); per-row metrics as host
        arrays of length ``n_rows``. ``self.complete`` says whether every row finished."""
        from jaxrobo import sharding

        mesh, n = self.mesh, self.n_padded
        host = sharding.pad_rows((key_data, agent_params, env_params), n)
        kd, ap, ep = sharding.put_batch(host, mesh)
        t0 = time.perf_counter()
        opts = self.options
        init = sharding.jit_batched(self._init, mesh, n, (kd, ap, ep), compiler_options=opts)
        runner = init.lower(kd, ap, ep).compile()(kd, ap, ep)
        chunk = sharding.jit_batched(self._chunk, mesh, n, (runner, ap, ep), donate=(0,), compiler_options=opts)
        chunk = chunk.lower(runner, ap, ep).compile()
        finish = sharding.jit_batched(self._finish, mesh, n, (runner, kd, ep), compiler_options=opts)
        finish = finish.lower(runner, kd, ep).compile()
        episodes = jax.jit(lambda r: jnp.min(r.episode))
        jax.block_until_ready(runner)
        self.compile_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        nepisodes = self.trainer.config.nepisodes
        for _ in range(self.trainer.max_chunks()):
            runner = chunk(runner, ap, ep)
            done = int(episodes(runner))
            if progress is not None:
                progress(done, nepisodes)
            if done >= nepisodes:
                break
            if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
                break
        self.complete = done >= nepisodes
        out = finish(runner, kd, ep)
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


def run_sweep(env_id: str, points: Sequence[Mapping[str, Any]], seeds: Sequence[int] = (0,),
              preset: str = "default", agent: str | None = None, overrides: Mapping[str, Any] | None = None,
              mesh: Any = None, eval_episodes: int = 0, n_last: int = 100,
              log: Callable[[str], None] | None = None,
              progress: Callable[[int, int], None] | None = None,
              compiler_options: dict[str, Any] | None = None, max_seconds: float | None = None) -> SweepResult:
    """Train every point × seed; rows grouped by static settings, one compiled program per group.

    ``points`` map swept keys to values (see :func:`classify`); ``overrides`` apply to every point (like
    ``--set``); ``max_seconds`` stops each group's training early (its rows then have ``episodes_done`` below
    ``nepisodes`` and the group ``complete: False``). Raises :class:`ConfigError` naming the key for any bad
    key or value, before compiling.
    """
    from jaxrobo.run import resolve

    log = log or (lambda _msg: None)
    overrides = dict(overrides or {})
    overrides.setdefault("record_episodes", True)
    if not seeds:
        raise ConfigError("--seeds: need at least one seed")
    swept, kinds, checked, groups = plan_groups(env_id, points)

    rows: list[dict[str, Any]] = []
    timings: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for g, (static, members) in enumerate(groups.items()):
        spec = resolve(env_id, preset, {**overrides, **{_bare(k): v for k, v in static}}, agent=agent)
        env, base_ap, base_ep = spec.env, spec.agent_params, spec.env.default_params
        bounds = [np.asarray(b) for b in env.state_bounds(base_ep)]
        agent_list, env_list, meta = [], [], []
        for i in members:
            point = checked[i]
            ap = base_ap.replace(**{_bare(k): v for k, v in point.items() if kinds[k].where == "agent"})
            ep = base_ep.replace(**{_bare(k): v for k, v in point.items() if kinds[k].where == "env"})
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
        key_data = np.stack([np.asarray(jax.random.key_data(jax.random.key(s))) for (_, s, _) in meta])
        trainer = Trainer(env, spec.config)
        group = GroupRunner(trainer, len(meta), mesh, eval_episodes, n_last, compiler_options)
        label = ", ".join(f"{k}={v}" for k, v in static) or "all"
        log(f"group {g + 1}/{len(groups)} [{label}]: {len(members)} configs × {len(seeds)} seeds × "
            f"{spec.config.n_envs} envs, {spec.config.nepisodes} episodes ≤ {spec.config.nsteps} steps")
        metrics = group.run(key_data, _stack(agent_list), _stack(env_list), progress, max_seconds)
        steps = int(metrics["env_steps"].astype(np.int64).sum())
        timings.append({"group": g, "static": dict(static), "rows": len(meta), "n_envs": spec.config.n_envs,
                        "compile_seconds": group.compile_seconds, "run_seconds": group.run_seconds,
                        "env_steps": steps, "env_steps_per_second": steps / max(group.run_seconds, 1e-9),
                        "complete": group.complete})
        log(f"  compiled in {group.compile_seconds:.1f} s; {steps:,} env steps in {group.run_seconds:.1f} s "
            f"({steps / max(group.run_seconds, 1e-9):,.0f} steps/s)")
        for r, (i, s, ap) in enumerate(meta):
            row: dict[str, Any] = {"config": i, "seed": s, "group": g}
            row.update(checked[i])
            row.update({k: float(getattr(ap, k)) for k in rules(AgentParams)})
            for m, values in metrics.items():
                v = values[r]
                row[m] = int(v) if np.issubdtype(values.dtype, np.integer) else float(v)
            rows.append(row)
    rows.sort(key=lambda r: (r["config"], r["seed"]))
    return SweepResult(env_id, swept, rows, timings, time.perf_counter() - t_all)


def _bare(key: str) -> str:
    return key.split(".", 1)[1] if key.startswith(("env.", "agent.")) else key


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
def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``jaxrobo sweep``."""
    parser.add_argument("--env", default="CartPoleStayUp-v0", help="environment id (see `jaxrobo list`)")
    parser.add_argument("--agent", default=None, help="qlearn | sarsa | expected_sarsa | double_q")
    parser.add_argument("--preset", default="default", help="parameter preset of the env's agent YAML")
    parser.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                        help="values of one swept key (repeatable; the grid is their product)")
    parser.add_argument("--random", type=int, default=0, metavar="N", help="N random points from the --range's")
    parser.add_argument("--range", action="append", metavar="KEY=LOW:HIGH[:log]", dest="ranges",
                        help="sampling range of one key for --random (repeatable)")
    parser.add_argument("--seeds", type=int, default=4, help="seeds per configuration (rows = configs × seeds)")
    parser.add_argument("--seed", type=int, default=0, help="first seed; seeds are SEED .. SEED+N-1")
    parser.add_argument("--n-envs", type=int, default=None, help="environments (tables) per row")
    parser.add_argument("--nepisodes", type=int, default=None, help="episodes per environment")
    parser.add_argument("--nsteps", type=int, default=None, help="step cap per episode")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="fixed override for every row")
    parser.add_argument("--eval-episodes", type=int, default=10,
                        help="greedy evaluation episodes of each row's first table (0: none)")
    parser.add_argument("--metric", default="final_return", choices=METRICS, help="what ranks configurations")
    parser.add_argument("--shard", choices=("auto", "on", "off"), default="auto",
                        help="split rows over all devices (auto: when there is more than one)")
    parser.add_argument("--out", default=None, help="output directory (default sweep_results/<env>_<time>)")
    parser.add_argument("--no-plots", action="store_true", help="skip the heatmap PNGs")


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


def run(args: argparse.Namespace) -> int:
    """``jaxrobo sweep``: train every row, write sweep.csv, summary.json and heatmaps, print the best."""
    from jaxrobo import sharding

    try:
        sharding.initialize_distributed()  # a no-op unless JAXROBO_COORDINATOR & co. are set (docs/scaling.md)
        if args.seeds < 1:
            raise ConfigError(f"--seeds {args.seeds}: must be >= 1")
        if args.eval_episodes < 0:
            raise ConfigError(f"--eval-episodes {args.eval_episodes}: must be >= 0")
        if args.metric.startswith("eval_") and args.eval_episodes == 0:
            raise ConfigError(f"--metric {args.metric}: needs --eval-episodes > 0")
        points = points_from_args(args)
        overrides = parse_overrides(args.set or [])
        for key, flag in (("n_envs", args.n_envs), ("nepisodes", args.nepisodes), ("nsteps", args.nsteps)):
            if flag is not None:
                overrides[key] = flag
        mesh = None
        if args.shard == "on" or (args.shard == "auto" and jax.device_count() > 1):
            mesh = sharding.make_mesh()
        seeds = list(range(args.seed, args.seed + args.seeds))
        out = args.out or os.path.join("sweep_results", f"{args.env}_{time.strftime('%Y%m%d-%H%M%S')}")
        print(f"{args.env}: {len(points)} configurations × {len(seeds)} seeds"
              f"{f' over {mesh.devices.size} devices' if mesh is not None else ''} → {out}")
        result = run_sweep(args.env, points, seeds, args.preset, args.agent, overrides, mesh,
                           args.eval_episodes, log=print)
    except (ConfigError, ValueError) as err:
        print(f"jaxrobo sweep: {err}", file=sys.stderr)
        return 2
    metric = args.metric
    if jax.process_index() != 0:
        return 0
    os.makedirs(out, exist_ok=True)
    write_csv(result, os.path.join(out, "sweep.csv"))
    best = result.best(metric)
    summary = {"env_id": args.env, "agent": args.agent, "preset": args.preset, "swept": result.swept,
               "seeds": seeds, "n_rows": len(result.rows), "wall_seconds": result.wall_seconds,
               "env_steps": result.env_steps, "env_steps_per_second": result.env_steps / max(result.wall_seconds, 1e-9),
               "groups": result.groups, "best": best, "argv": sys.argv}
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2, default=str)
    plots = [] if args.no_plots else plot_sweep(result, out, metric)
    print(f"{len(result.rows)} rows, {result.env_steps:,} env steps in {result.wall_seconds:.1f} s "
          f"({summary['env_steps_per_second']:,.0f} steps/s incl. compile)")
    print("best configuration: " + ", ".join(f"{k}={_fmt(best[k])}" for k in result.swept) +
          f"  ({metric} {best['mean']:.1f} ± {best['std']:.1f} over {best['seeds']} seeds)")
    print(f"results: {os.path.join(out, 'sweep.csv')}" + (f"; plots: {', '.join(plots)}" if plots else ""))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxrobo sweep", description=__doc__.split("\n\n")[0])
    configure_parser(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
