"""Do the default presets meet their learning targets under the step budget as under the episode budget?

For each task, ``--runs`` independent runs of its default preset (seeds BASE..BASE+runs-1, each the run
``jaxrobo train --env ID --seed S`` would train) train side by side as one vmapped computation, first under the
seed's per-env episode budget, then under a step budget (``total_steps``) of the same experience: the median over
runs of the env steps the episode budget used, rounded up to whole chunks of every env. Each run is then judged as
``jaxrobo train`` judges it: its tables are evaluated greedily by the driver's own evaluation (the shared table,
or the first ``eval_envs`` tables and the best of them again on fresh episodes), and the figure is the task's
declared learning target (``learning_target``: success rate, mean length or mean return against its threshold).
The headline per task and budget is the **median run** and the share of runs meeting the target.

    python benchmarks/learning_targets.py --device gpu --runs 16 --seed-base 1000
    python benchmarks/learning_targets.py --envs ArmReach-v0 --runs 2 --set nepisodes=20     # a CPU smoke run
    python benchmarks/learning_targets.py --envs CartPoleStayUp-v0 --total-steps 16128000    # the step budget only
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402

if __name__ == "__main__":  # the platform is chosen before JAX starts
    _pre = argparse.ArgumentParser(add_help=False)
    _pre.add_argument("--device", choices=("cpu", "gpu"), default=None)
    _common.select_device(_pre.parse_known_args()[0].device)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _population import train_population  # noqa: E402

from jaxrobo.task.env import ranking  # noqa: E402
from jaxrobo.training import driver  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402
from jaxrobo.training.trainer import Trainer  # noqa: E402

ENVS = ("CartPoleStayUp-v0", "QuadcopterGoto-v2", "ArmReach-v0")


def train_and_judge(env_id: str, runs: int, seed_base: int, overrides: dict) -> dict:
    """Train ``runs`` runs of ``env_id``'s default preset (with ``overrides``) as one vmapped computation and judge
    each by its learning target: a dict with the per-run ``score``, ``met``, ``env_steps``, ``useful_share`` and
    the ``seconds`` of training (compile included) and evaluation."""
    spec = resolve(env_id, overrides=overrides)
    env, config = spec.env, spec.config
    print(f"{env_id}: {runs} runs of the default preset, budget "
          + ('total_steps ' + format(config.total_steps, ',') if config.total_steps
             else 'nepisodes ' + str(config.nepisodes))
          + " ...", flush=True)
    target = getattr(env, "learning_target", None)
    if target is None:
        raise ValueError(f"{env_id} declares no learning_target")
    seeds = list(range(seed_base, seed_base + runs))
    population = train_population(spec, seeds)
    trainer, runner = population.trainer, population.runner
    env_steps = np.asarray(jax.device_get(runner.env_steps), np.int64).reshape(runs, -1).sum(axis=1)
    t1 = time.perf_counter()
    scores = np.asarray(judge(trainer, runner, seeds, env.default_params, target))
    higher = ranking(target).higher
    met = target.reached(scores)
    chunks = population.loop.chunks_done
    slots = chunks * config.chunk_steps * config.n_envs
    return {"target": target.description, "metric": target.metric, "threshold": float(target.threshold),
            "n_envs": config.n_envs, "chunk_steps": config.chunk_steps, "nepisodes": config.nepisodes,
            "total_steps": config.total_steps,
            "budget": trainer.budget, "seeds": seeds, "score": [round(float(s), 4) for s in scores],
            "met": [bool(m) for m in met], "env_steps": env_steps.tolist(),
            "useful_share": [round(float(s) / slots, 4) for s in env_steps],
            "median_score": float(np.median(scores)),
            "worst_score": float(scores.min() if higher else scores.max()), "share_met": float(met.mean()),
            "train_seconds": round(population.seconds, 2), "eval_seconds": round(time.perf_counter() - t1, 2),
            "execution_plan": repr(trainer.plan)}


def judge(trainer: Trainer, runner, seeds: list[int], env_params, target) -> list[float]:
    """Each run's learning-target figure, judged as :func:`jaxrobo.training.driver.evaluate_tables` judges a run of
    ``jaxrobo train --seed S`` (the driver's keys, tables, best table and figure:
    :func:`~jaxrobo.training.driver.evaluation_keys`, :func:`~jaxrobo.training.driver.choose_table`), for all runs
    in one vmapped program: the figure of the shared table or of the best evaluated one
    (:func:`~jaxrobo.training.driver.pick_tables` of each run's carry, ``runner``), or that best table's
    figure on fresh episodes where the driver flies it again for the run's figure."""
    config = trainer.config
    shared = config.shared_table
    n_eval = driver.evaluated_tables(config)
    _, tables = jax.jit(jax.vmap(functools.partial(driver.pick_tables, trainer)))(runner)
    run_keys = [driver.evaluation_keys(jax.random.key(s), n_eval) for s in seeds]  # [(per table, fresh)] per run
    keys, fresh = jnp.stack([k for k, _ in run_keys]), jnp.stack([f for _, f in run_keys])
    one_run = jax.vmap(trainer.evaluate_episodes, in_axes=(0, None if shared else 0, None, None))
    out = jax.device_get(jax.jit(jax.vmap(one_run, in_axes=(0, 0, None, None)), static_argnums=2)(
        keys, tables, config.eval_episodes, env_params))
    runs = [{k: out[k][i] for k in ("return", "length", "arrived") if k in out} for i in range(len(seeds))]
    best, figures = zip(*(driver.choose_table(driver.table_figures(run, target), target) for run in runs))
    if all(f is not None for f in figures):
        return list(figures)
    if target.metric not in ("mean_length", "mean_return"):
        raise ValueError(f"{trainer.env.name}: its greedy evaluation records no {target.metric}")
    chosen = jax.tree.map(lambda x: x[np.arange(len(seeds)), np.asarray(best)], tables)
    returns, lengths = jax.device_get(jax.jit(jax.vmap(trainer.evaluate, in_axes=(0, 0, None, None)),
                                              static_argnums=2)(fresh, chosen, config.eval_episodes, env_params))
    figure = np.asarray(lengths if target.metric == "mean_length" else returns)
    return [float(v) for v in figure.astype(np.float64).mean(axis=1)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default=None)
    ap.add_argument("--envs", default=",".join(ENVS), help="comma list of env ids with a learning target")
    ap.add_argument("--runs", type=int, default=16, help="runs per task and budget (>= 1)")
    ap.add_argument("--seed-base", type=int, default=1000, help="first seed (default 1000: seeds nobody tuned on)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="preset override (both budgets)")
    ap.add_argument("--total-steps", type=int, default=None, metavar="N",
                    help="the step budget of each run, given: only the step-budget runs train (default: the median "
                         "env steps of the episode budget's runs, which train first)")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/learning_targets.json)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error(f"--runs must be >= 1 (got {args.runs})")
    if args.total_steps is not None and args.total_steps < 1:
        ap.error(f"--total-steps must be >= 1 (got {args.total_steps})")
    from jaxrobo.core.config import parse_overrides

    base = parse_overrides(args.set)
    if "total_steps" in base or "total_episodes" in base:
        ap.error("--set total_steps/total_episodes: the benchmark sets the step budget itself")
    rows = []
    for env_id in [e for e in args.envs.split(",") if e]:
        if args.total_steps is None:
            episodes = train_and_judge(env_id, args.runs, args.seed_base, base)
            # Whole chunks of every env: a last chunk cut short would leave slots idle that the budget could use.
            n = episodes["n_envs"] * episodes["chunk_steps"]
            steps_budget = int(-(-int(np.median(episodes["env_steps"])) // n) * n)
            budgets = [episodes]
        else:
            steps_budget, budgets = args.total_steps, []
        steps = train_and_judge(env_id, args.runs, args.seed_base, {**base, "total_steps": steps_budget})
        for row in budgets + [steps]:
            row["env"] = env_id
            rows.append(row)
            print(f"{env_id} [{row['budget']}{'' if row['budget'] == 'episodes' else f' {steps_budget:,}'}]: "
                  f"target {row['target']}; median {row['median_score']:.3f}, worst {row['worst_score']:.3f}, "
                  f"{row['share_met']:.0%} of {args.runs} runs meet it; useful slots median "
                  f"{np.median(row['useful_share']):.1%}; train {row['train_seconds']:.1f} s", flush=True)
    _common.write_json({"device": jax.devices()[0].device_kind, "argv": sys.argv, "runs": args.runs,
                        "seed_base": args.seed_base, "rows": rows}, args.out, "learning_targets.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
