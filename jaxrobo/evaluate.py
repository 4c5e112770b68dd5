"""``jaxrobo eval RUN``: a trained policy on fresh episodes over a grid of physical shifts (robustness evaluation).

Reads a run directory (a tabular run's ``config.yaml`` + ``qtables.npz``, or a ``--agent ppo|sac`` run's saved
policy) and flies its greedy (deterministic) policy on the run's task with domain randomisation switched on
(:mod:`jaxrobo.task.randomise`), each physical quantity pinned: ``--shift mass=0.8,1.0,1.2`` evaluates at each
of those values while every other randomisable quantity stays at its nominal value (the task's default range).
Each ``--shift`` is one axis, evaluated on its own. Every value flies the same episodes (the same keys, so the
starts, goals and obstacles are the same and only the physics differs).

The figure follows the task's :attr:`jaxrobo.task.env.Env.learning_target`: the share of successful episodes for
a ``success_rate`` target, else the mean return (or length). A tabular run evaluates its first ``--tables``
tables (each an independent learner): the table reports the mean over them, and the worst and best table.
Writes ``robustness.csv`` (``shift,value,metric,mean,worst,best,tables,episodes``) and ``robustness.png`` into
``--out`` (default ``<RUN>/robustness``), and prints the table. ``--out`` is checked before anything is read or
flown: an earlier evaluation's files there are replaced only with ``--overwrite``.
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
from typing import Any, Sequence

import numpy as np

#: The columns of ``robustness.csv``.
COLUMNS = ("shift", "value", "metric", "mean", "worst", "best", "tables", "episodes")
#: Most tables one evaluation flies (each flies ``--episodes`` episodes per value).
MAX_TABLES = 4096
#: Tables evaluated without ``--tables`` (fewer where the run has fewer).
DEFAULT_TABLES = 8


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="training run directory (jaxrobo train: config.yaml and qtables.npz, or a "
                                        "ppo/sac run's policy)")
    parser.add_argument("--shift", action="append", metavar="NAME=V1,V2,...", default=None,
                        help="a randomisable quantity and the values to evaluate at, e.g. mass=0.8,1.0,1.2 or "
                             "wind=0,0.5,1 (repeatable; names: the task's rand_* ranges without the prefix)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per table and value")
    parser.add_argument("--tables", type=int, default=None,
                        help=f"how many of the run's tables to evaluate (default: {DEFAULT_TABLES}, or all the run "
                             "has where fewer)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes (the same for every value)")
    parser.add_argument("--out", default=None, help="output directory (default <RUN>/robustness)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace robustness.csv and robustness.png where --out holds them already")


def parse_shifts(items: Sequence[str] | None, params: Any) -> dict[str, list[float]]:
    """``["mass=0.8,1.2"]`` → ``{"mass": [0.8, 1.2]}``, each value checked against its range's declared limits."""
    from jaxrobo.core.config import ConfigError, coerce
    from jaxrobo.core.struct import rules
    from jaxrobo.task import randomise

    known = randomise.range_fields(type(params))
    if not items:
        raise ConfigError(f"--shift: give at least one NAME=V1,V2,... (names: {', '.join(known) or 'none'})")
    table = rules(type(params))
    out: dict[str, list[float]] = {}
    for item in items:
        name, sep, text = (s.strip() for s in item.partition("="))
        if not sep or not text:
            raise ConfigError(f"--shift {item!r}: expected NAME=V1,V2,...")
        if name not in known:
            raise ConfigError(f"--shift {name}: not a randomisable quantity of {type(params).__name__}; "
                              f"allowed: {', '.join(known) or 'none'}")
        if name in out:
            raise ConfigError(f"--shift {name}: given twice")
        values = []
        for v in text.split(","):
            try:
                x = float(v)
            except ValueError:
                raise ConfigError(f"--shift {name}={v!r}: expected a number") from None
            values.append(coerce(f"--shift {name}", [x, x], table[randomise.PREFIX + name])[0])
        out[name] = values
    return out


def _load(run_dir: str, tables: int | None) -> tuple[Any, Any, Any]:
    """``(env, policies, kind)``: the run's env, a function ``(q_or_none, key, obs) -> action`` maker, and the
    run's tables (``[T, n_tables, n_states, n_actions]``) or None for a deep run."""
    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError
    from jaxrobo.show import _load_deep_run, _load_run, check_table

    if not os.path.isdir(run_dir):
        raise ConfigError(f"run directory {run_dir!r} does not exist (or is not a directory)")
    if deep.is_deep_run(run_dir):
        if tables is not None:  # silently ignored otherwise
            raise ConfigError(f"--tables {tables}: a ppo/sac run has one policy, no tables; drop the flag")
        spec, policy = _load_deep_run(run_dir, 0)
        return spec, policy, None
    spec, _, q = _load_run(run_dir)
    if tables is not None and tables > q.shape[0]:  # was cut to the run's count without a word
        raise ConfigError(f"--tables {tables}: the run has {q.shape[0]} tables; expected 1..{q.shape[0]}")
    n = min(DEFAULT_TABLES if tables is None else tables, q.shape[0])
    for t in range(n):
        check_table(q, t, os.path.join(run_dir, "qtables.npz"))
    return spec, None, q[:n]


def randomised_env(env: Any) -> Any:
    """``env`` with domain randomisation switched on (same options and parameters otherwise), or ConfigError."""
    from jaxrobo.core.config import ConfigError

    if not hasattr(env.options, "randomise"):
        raise ConfigError(f"{env.name}: the task has no randomise option; it cannot be evaluated on shifted physics")
    try:
        out = type(env)(env.options.replace(randomise=True), env.default_params)
    except ValueError as err:
        raise ConfigError(f"{env.name}: {err}") from None
    out.spec = env.spec
    return out


def evaluate(spec: Any, q: np.ndarray | None, policy: Any, shifts: dict[str, list[float]], episodes: int,
             seed: int) -> list[dict[str, Any]]:
    """One row per shift value: the target's metric, mean over the tables, and the worst and best table."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.task import randomise
    from jaxrobo.task.rollout import greedy_policy, rollout
    from jaxrobo.training.trainer import make_discretiser_for

    env = randomised_env(spec.env)
    target = getattr(env, "learning_target", None)
    metric = target.metric if target is not None else "mean_return"
    higher = target is None or target.better == "higher"
    nominal = {f.name: f.default for f in __import__("dataclasses").fields(type(env.default_params))}
    base = env.default_params.replace(**{randomise.PREFIX + n: nominal[randomise.PREFIX + n]
                                         for n in randomise.range_fields(type(env.default_params))})

    def score(last: Any, out: dict) -> jax.Array:
        if metric == "success_rate":
            return jnp.mean(jnp.asarray(last.task.arrived, jnp.float32))
        if metric == "mean_length":
            return jnp.mean(out["length"].astype(jnp.float32))
        return jnp.mean(out["return"])

    if q is not None:
        disc = make_discretiser_for(spec.env, spec.config)

        def one(qt, key, params):
            out = rollout(env, greedy_policy(qt, disc), key, episodes, params=params)
            return score(out["last"], out)

        run = jax.jit(jax.vmap(one, in_axes=(0, None, None)))
        tables = jnp.asarray(q)
    else:
        def single(_, key, params):
            out = rollout(env, policy, key, episodes, params=params)
            return score(out["last"], out)[None]

        run, tables = jax.jit(single), None
    key = jax.random.key(seed)
    rows = []
    for name, values in shifts.items():
        for v in values:
            got = np.asarray(run(tables, key, randomise.pinned(base, {name: v})))
            lo, hi = float(got.min()), float(got.max())  # best and worst the way the target improves
            rows.append({"shift": name, "value": v, "metric": metric, "mean": float(got.mean()),
                         "worst": lo if higher else hi, "best": hi if higher else lo, "tables": int(got.size),
                         "episodes": episodes})
    return rows


def write(rows: list[dict[str, Any]], out_dir: str, title: str) -> tuple[str, str]:
    """``robustness.csv`` and ``robustness.png`` in ``out_dir``."""
    from jaxrobo.pictures.plots import robustness_figure

    os.makedirs(out_dir, exist_ok=True)
    from jaxrobo.io import rundir

    path = os.path.join(out_dir, "robustness.csv")

    def table(f) -> None:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow(r)

    rundir.atomic_write(path, table, mode="w")  # a stop while writing keeps the earlier table whole
    png = os.path.join(out_dir, "robustness.png")
    robustness_figure(rows, png, title)
    return path, png


#: What ``jaxrobo eval`` writes into ``--out``.
OUTPUTS = ("robustness.csv", "robustness.png")


def check_out(out: str, overwrite: bool) -> None:
    """``--out`` can be written, and holds no earlier evaluation unless ``overwrite`` (ConfigError naming it): a
    table the user kept from an earlier evaluation is not replaced without being asked, nor found unwritable
    after the flights."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io import rundir

    rundir.check_writable(out, "--out", directory=True)  # a file there or on the way
    there = [name for name in OUTPUTS if os.path.lexists(os.path.join(out, name))]
    for name in there:
        if os.path.isdir(os.path.join(out, name)) and not os.path.islink(os.path.join(out, name)):
            raise ConfigError(f"--out {out}: {name} is a directory; jaxrobo eval writes a file of that name")
    if there and not overwrite:
        raise ConfigError(f"--out {out}: holds {' and '.join(there)} already; give --overwrite to replace "
                          f"{'them' if len(there) > 1 else 'it'}, or another --out")


def run(args: argparse.Namespace) -> int:
    from jaxrobo.core.config import ConfigError

    try:
        if not 1 <= args.episodes <= 1_000_000:
            raise ConfigError(f"--episodes {args.episodes}: expected 1..1000000")
        if args.tables is not None and not 1 <= args.tables <= MAX_TABLES:
            raise ConfigError(f"--tables {args.tables}: expected 1..{MAX_TABLES}")
        from jaxrobo.core.struct import INT32_MAX

        if not 0 <= args.seed <= INT32_MAX:
            raise ConfigError(f"--seed {args.seed}: expected an integer in 0..{INT32_MAX}")
        if not os.path.isdir(args.run_dir):  # before --out, whose default lies in it
            raise ConfigError(f"run directory {args.run_dir!r} does not exist (or is not a directory)")
        out = args.out if args.out is not None else os.path.join(args.run_dir, "robustness")
        check_out(out, args.overwrite)
        spec, policy, q = _load(args.run_dir, args.tables)
        shifts = parse_shifts(args.shift, spec.env.default_params)
        randomised_env(spec.env)  # refuse a task without randomisation before anything compiles
    except ConfigError as err:
        print(f"jaxrobo eval: {err}", file=sys.stderr)
        return 2
    rows = evaluate(spec, q, policy, shifts, args.episodes, args.seed)
    what = "greedy tables" if q is not None else f"{spec.agent} policy"
    print(f"{spec.env_id}: {what} of {args.run_dir} on shifted physics ({rows[0]['metric']}, "
          f"{args.episodes} episodes per {'table' if q is not None else 'value'})")
    print(f"{'shift':>12s} {'value':>8s} {'mean':>8s} {'worst':>8s} {'best':>8s}")
    for r in rows:
        print(f"{r['shift']:>12s} {r['value']:8.3g} {r['mean']:8.3f} {r['worst']:8.3f} {r['best']:8.3f}")
    path, png = write(rows, out, f"{spec.env_id}: {what}")
    print(f"wrote {path} and {png}")
    return 0
