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
"""
from __future__ import annotations

import argparse
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

from jaxrobo.task.env import ranking  # noqa: E402
from jaxrobo.training import driver  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402
from jaxrobo.training.trainer import Trainer  # noqa: E402

ENVS = ("CartPoleStayUp-v0", "QuadcopterGoto-v2", "ArmReach-v0")


def train_population(env_id: str, runs: int, seed_base: int, overrides: dict) -> dict:
    """Train ``runs`` runs of ``env_id``'s default preset (with ``overrides``) as one vmapped computation and judge
    each by its learning target: a dict with the per-run ``score``, ``met``, ``env_steps``, ``useful_share`` and
    the ``seconds`` of training (compile included) and evaluation."""
    spec = resolve(env_id, overrides=overrides)
    env, config = spec.env, spec.config
    print(f"{env_id}: {runs} runs of the default preset, budget "
          f"{'total_steps ' + format(config.total_steps, ',') if config.total_steps else 'nepisodes ' + str(config.nepisodes)}"
          " ...", flush=True)
    target = getattr(env, "learning_target", None)
    if target is None:
        raise ValueError(f"{env_id} declares no learning_target")
    trainer = Trainer(env, config)
    seeds = list(range(seed_base, seed_base + runs))
    keys = jnp.stack([jax.random.key(s) for s in seeds])
    ap_, ep = spec.agent_params, env.default_params
    t0 = time.perf_counter()
    runner = jax.jit(jax.vmap(trainer.init, in_axes=(0, None, None)))(keys, ap_, ep)
    plan = trainer.plan
    chunk = driver.compile_under(plan, jax.jit(jax.vmap(trainer.run_chunk, in_axes=(0, None, None)),
                                               donate_argnums=0, compiler_options=plan.xla_options), runner, ap_, ep)
    total, unit = trainer.budget_total
    loop = driver.run_chunks(lambda r: chunk(r, ap_, ep), runner, trainer.max_chunks(),
                             read=driver.compiled_progress(runner), total=total, unit=unit)
    runner = loop.carry
    env_steps = np.asarray(jax.device_get(runner.env_steps), np.int64).reshape(runs, -1).sum(axis=1)
    train_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    scores = judge(trainer, runner.agent, seeds, ep, target)
    scores = np.asarray(scores)
    higher = ranking(target).higher
    met = scores >= target.threshold if higher else scores <= target.threshold
    chunks = loop.chunks_done
    slots = chunks * config.chunk_steps * config.n_envs
    return {"target": target.description, "metric": target.metric, "threshold": float(target.threshold),
            "n_envs": config.n_envs, "chunk_steps": config.chunk_steps, "nepisodes": config.nepisodes, "total_steps": config.total_steps,
            "budget": trainer.budget, "seeds": seeds, "score": [round(float(s), 4) for s in scores],
            "met": [bool(m) for m in met], "env_steps": env_steps.tolist(),
            "useful_share": [round(float(s) / slots, 4) for s in env_steps],
            "median_score": float(np.median(scores)),
            "worst_score": float(scores.min() if higher else scores.max()), "share_met": float(met.mean()),
            "train_seconds": round(train_s, 2), "eval_seconds": round(time.perf_counter() - t1, 2),
            "execution_plan": repr(plan)}


def judge(trainer: Trainer, agent, seeds: list[int], env_params, target) -> list[float]:
    """Each run's learning-target figure, judged as :func:`jaxrobo.training.driver.evaluate_tables` judges a run of
    ``jaxrobo train --seed S`` (the same keys, tables and selection), for all runs in one vmapped program: the
    shared table's figure, or for per-env tables the best of the first ``eval_envs`` (by mean return) flown again
    on fresh episodes."""
    config = trainer.config
    shared = config.shared_table
    n_eval = 1 if shared else min(config.eval_envs, config.n_envs)
    tables = agent if shared else jax.tree.map(lambda x: x[:, :n_eval], agent)
    run_keys = [jax.random.key(s) for s in seeds]
    keys = jnp.stack([jax.random.split(jax.random.fold_in(k, 1), n_eval) for k in run_keys])
    one_run = jax.vmap(trainer.evaluate_episodes, in_axes=(0, None if shared else 0, None, None))
    out = jax.device_get(jax.jit(jax.vmap(one_run, in_axes=(0, 0, None, None)), static_argnums=2)(
        keys, tables, config.eval_episodes, env_params))
    per_table = {"mean_length": np.asarray(out["length"]), "mean_return": np.asarray(out["return"])}
    if "arrived" in out:
        per_table["success_rate"] = np.asarray(out["arrived"])
    if n_eval > 1 and target.metric in ("mean_length", "mean_return"):
        rank = ranking(target)  # the driver's choice of the best table, run by run
        best = np.asarray([rank.best_table({k: v[i] for k, v in per_table.items()}) for i in range(len(seeds))])
        chosen = jax.tree.map(lambda x: x[np.arange(len(seeds)), best], tables)
        fresh = jnp.stack([jax.random.fold_in(k, 2) for k in run_keys])
        returns, lengths = jax.device_get(jax.jit(jax.vmap(trainer.evaluate, in_axes=(0, 0, None, None)),
                                                  static_argnums=2)(fresh, chosen, config.eval_episodes, env_params))
        figure = np.asarray(lengths if target.metric == "mean_length" else returns)
        return [float(v) for v in figure.astype(np.float64).mean(axis=1)]
    # the shared table, or the best evaluated table by the target's own figure
    figure = per_table[target.metric].astype(np.float64).mean(axis=2)
    return [float(v) for v in (figure.max(axis=1) if ranking(target).higher else figure.min(axis=1))]


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
            episodes = train_population(env_id, args.runs, args.seed_base, base)
            # Whole chunks of every env: a last chunk cut short would leave slots idle that the budget could use.
            n = episodes["n_envs"] * episodes["chunk_steps"]
            steps_budget = int(-(-int(np.median(episodes["env_steps"])) // n) * n)
            budgets = [episodes]
        else:
            steps_budget, budgets = args.total_steps, []
        steps = train_population(env_id, args.runs, args.seed_base, {**base, "total_steps": steps_budget})
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
