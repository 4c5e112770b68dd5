"""Does the Goto task learn in every run? Train independent runs at once, fly each on fresh goals, report the median.

Each run is the env's default preset (one table shared by ``n_envs`` environments); ``--runs`` of them train side
by side as one vmapped computation, each from its own seed (``--seed-base`` .. ``--seed-base`` + runs - 1, or
the list ``--seeds``). Every run's own greedy table then flies the same ``--episodes`` *fresh* random goals
(obstacle present, a key no run trained on): the headline is the **median over runs** of that arrival rate, with
every run listed, the min / max and the worst seeds. A secondary line keeps the older best-of-population figure
(the run best on ``--select-episodes`` selection goals, re-flown on the fresh goals), which says what selection
can reach, not what one run does.

    python benchmarks/goto_learning.py --env QuadcopterGoto-v2 --runs 16      # CPU or GPU
    python benchmarks/goto_learning.py --env QuadcopterGoto-v1 --runs 32      # the original task
    python benchmarks/goto_learning.py --fused pallas                          # the same runs through the kernel
    python benchmarks/goto_learning.py --runs 64 --seed-base 1000              # prints the worst seeds
    python benchmarks/goto_learning.py --seeds 1015,1051                       # retrain chosen seeds

``--fused pallas``: train under ``ExecutionPlan(fused="pallas")`` with the task's whole step as one kernel where it
has one (``task_kernel``), which the presets' small batches do not get by default, so that the learning of the
kernel's path can be compared with the plain path's.
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _population import train_population  # noqa: E402

from jaxrobo.task.rollout import greedy_policy, random_policy, rollout  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402

ENVS = ("QuadcopterGoto-v1", "QuadcopterGoto-v2")
FRESH_KEY = 123_456  # the fresh evaluation goals: no run trains or selects on this key
TARGET = 0.8


def spread(rates) -> dict[str, float]:
    """``min`` / ``median`` / ``max`` / ``mean`` of per-run rates and the share of runs at or above ``TARGET``."""
    r = np.asarray(rates, np.float64)
    if r.ndim != 1 or r.size == 0:
        raise ValueError(f"rates has shape {r.shape}; expected one rate per run (at least one run)")
    return {"min": float(r.min()), "median": float(np.median(r)), "max": float(r.max()), "mean": float(r.mean()),
            "share_of_runs_at_target": float((r >= TARGET).mean())}


def train(env_id: str, seeds: list[int], overrides: dict,
          fused: str = "default") -> tuple[object, object, np.ndarray, float]:
    """Train one run of ``env_id``'s default preset per seed in ``seeds``, as one vmapped computation
    (:func:`_population.train_population`): ``(spec, trainer, q [runs, n_tables, S, A], seconds)`` (seconds
    include the compile). ``fused``: ``default`` (the plan ``for_run`` builds), or ``off``/``pallas`` (that
    choice; ``pallas`` with the task's kernel where it has one)."""
    from jaxrobo.speed.plan import ExecutionPlan, task_kernel

    spec = resolve(env_id, overrides={"eval_episodes": 0, **overrides})
    if not spec.config.shared_table:
        raise ValueError(f"{env_id}: the benchmark expects a preset with shared_table: true (one table per run)")
    plan = ExecutionPlan.for_run(spec.env, spec.config)
    if fused != "default":
        plan = plan.replace(fused=fused, task_kernel=fused == "pallas" and task_kernel(spec.env))
    runs = train_population(spec, seeds, plan)
    q = np.asarray(runs.runner.agent.q)  # [runs, n_tables, S, A]: the one shared table of each run
    return spec, runs.trainer, q, runs.seconds


def evaluate(env, disc, q: np.ndarray, key: jax.Array, episodes: int) -> dict[str, np.ndarray]:
    """Every run's greedy table flies the same ``episodes`` goals (drawn from ``key``): per-run ``success``,
    ``failure``, ``timeout`` rates and ``mean_steps``, each ``[runs]``. The key is an argument of the compiled
    flight, not a constant in it: the fresh and the selection flights of one size share one compile."""
    def one(table, key):
        last = rollout(env, greedy_policy(table, disc), key, episodes)["last"]
        arrived, crashed = last.task.arrived, last.task.crashed
        return {"success": arrived.mean(), "failure": crashed.mean(), "timeout": (~arrived & ~crashed).mean(),
                "mean_steps": last.steps.mean()}
    flights = jax.jit(jax.vmap(one, in_axes=(0, None)))
    return {k: np.asarray(v) for k, v in flights(jnp.asarray(q), key).items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="QuadcopterGoto-v2", choices=ENVS, help="the Goto task to train")
    ap.add_argument("--runs", type=int, default=16, help="independent training runs (seeds BASE..BASE+runs-1)")
    ap.add_argument("--seed-base", type=int, default=0,
                    help="first seed (each run's seed is that of `jaxrobo train --seed S`); e.g. 1000 for seeds "
                         "nobody tuned on")
    ap.add_argument("--seeds", default=None, metavar="S1,S2,...",
                    help="train exactly these seeds (comma-separated; replaces --runs and --seed-base), e.g. the "
                         "worst seeds of a larger run")
    ap.add_argument("--episodes", type=int, default=200, help="fresh evaluation goals flown by every run's table")
    ap.add_argument("--select-episodes", type=int, default=100,
                    help="selection goals for the secondary best-of-population line")
    ap.add_argument("--fused", default="default", choices=("default", "off", "pallas"),
                    help="the plan's fused choice (default: as for_run builds it)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="preset override")
    ap.add_argument("--fly-set", action="append", default=[], metavar="KEY=VALUE",
                    help="env override for the evaluation flights only, after --set's (e.g. tables trained on "
                         "nominal physics flown under randomised physics: --fly-set randomise=true --fly-set "
                         "rand_wind=[0,0.6])")
    ap.add_argument("--out", default=None,
                    help="JSON path (default benchmarks/results/<device>/goto_learning_<env>.json)")
    args = ap.parse_args(argv)
    if args.seeds is None:
        seeds = list(range(args.seed_base, args.seed_base + args.runs))
    else:
        try:
            seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        except ValueError:
            ap.error(f"--seeds takes whole numbers separated by commas (got {args.seeds!r})")
        if not seeds:
            ap.error("--seeds names no seed")
        args.runs = len(seeds)
    for name in ("runs", "episodes", "select_episodes"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1 (got {getattr(args, name)})")
    from jaxrobo.core.config import parse_overrides

    overrides, fly = parse_overrides(args.set), parse_overrides(args.fly_set)
    probe = resolve(args.env)
    for key in fly:  # env keys only: a learner or loop key would change nothing the flights do
        if not (hasattr(probe.env.default_params, key) or hasattr(probe.env.options, key)):
            ap.error(f"--fly-set {key}: not a parameter or option of {args.env}'s env (the flights change only "
                     "the env)")
    spec, trainer, q, train_s = train(args.env, seeds, overrides, args.fused)
    env, disc = spec.env, trainer.disc
    if fly:
        env = resolve(args.env, overrides={"eval_episodes": 0, **overrides, **fly}).env
        if env.observation_space().shape != spec.env.observation_space().shape:
            ap.error(f"--fly-set {', '.join(fly)}: changes the observation the tables were trained on")
    fresh = evaluate(env, disc, q, jax.random.key(FRESH_KEY), args.episodes)
    select = evaluate(env, disc, q, jax.random.key(10_000), args.select_episodes)
    best = int(np.argmax(select["success"]))
    rand = jax.jit(lambda k: rollout(env, random_policy(env.num_actions), k, args.episodes)["last"])(
        jax.random.key(FRESH_KEY))
    r3 = lambda x: round(float(x), 3)  # noqa: E731
    out = {"device": jax.devices()[0].device_kind, "env": args.env, "runs": args.runs,
           "n_envs": spec.config.n_envs, "nepisodes": spec.config.nepisodes, "fresh_episodes": args.episodes,
           "execution_plan": repr(trainer.plan),
           "train_seconds": round(train_s, 2),
           "fresh_success": {k: r3(v) for k, v in spread(fresh["success"]).items()},
           "seeds": seeds,
           "overrides": args.set,
           "fly_overrides": args.fly_set,
           "fresh_success_per_run": [r3(v) for v in fresh["success"]],
           "fresh_failure_per_run": [r3(v) for v in fresh["failure"]],
           "fresh_timeout_per_run": [r3(v) for v in fresh["timeout"]],
           "best_of_population": {"run": best, "selection_success": r3(select["success"][best]),
                                  "fresh_success": r3(fresh["success"][best])},
           "random_policy_fresh_success": r3(np.asarray(rand.task.arrived).mean())}
    s = out["fresh_success"]
    print(f"{args.env}: {args.runs} runs x {spec.config.n_envs} envs x {spec.config.nepisodes} episodes, "
          f"trained in {train_s:.1f} s (compile included) on {out['device']}")
    print("fresh-goal arrival rate per run: " + " ".join(f"{v:.3f}" for v in out["fresh_success_per_run"]))
    print(f"MEDIAN {s['median']:.3f}  (min {s['min']:.3f}, max {s['max']:.3f}; "
          f"{s['share_of_runs_at_target']:.0%} of runs >= {TARGET:.0%})")
    order = np.argsort(fresh["success"], kind="stable")[:8]
    worst = [(out["seeds"][i], float(fresh["success"][i])) for i in order]
    out["worst_seeds"] = [{"seed": sd, "fresh_success": r3(v)} for sd, v in worst]
    print("WORST seeds (fresh-goal arrival rate): " + ", ".join(f"seed {sd} {v:.3f}" for sd, v in worst))
    print(f"secondary, best of population: run {best} ({out['best_of_population']['selection_success']:.3f} on "
          f"{args.select_episodes} selection goals) -> {out['best_of_population']['fresh_success']:.3f} on the fresh "
          f"goals; random policy {out['random_policy_fresh_success']:.3f}")
    _common.write_json(out, args.out, f"goto_learning_{args.env}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
