"""Does ArmReach-v0 learn? Train several independent runs at once and report the MEDIAN run on fresh goals.

Each run is the ``default`` preset (one table shared by ``n_envs`` environments); ``--runs`` of them train side
by side as one vmapped computation, each from its own seed (0..runs-1). Every trained table then runs
``--episodes`` greedy episodes on fresh random starts and goals (the same evaluation keys for every run, none
used in training), and the benchmark reports each run's reach rate, their median and whether the median meets
the task's declared learning target (``ArmReach.learning_target``: success_rate >= 0.8). No run is selected:
the median is what one run of ``jaxrobo train`` can be expected to reach. The random policy's rate is reported
beside it.

    python benchmarks/arm_learning.py                     # 8 runs, CPU-sized
    python benchmarks/arm_learning.py --runs 32           # GPU
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402
from _population import train_population  # noqa: E402

from jaxrobo.task.rollout import greedy_policy, random_policy, rollout  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402

ENV_ID = "ArmReach-v0"
#: Evaluation keys: apart from the training seeds (0..runs-1), the same for every run.
EVAL_SEED = 123_456


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8, help="independent training runs (seeds BASE..BASE+runs-1), >= 1")
    ap.add_argument("--seed-base", type=int, default=0, help="first seed (e.g. 1000 for seeds nobody tuned on)")
    ap.add_argument("--episodes", type=int, default=200, help="fresh greedy evaluation episodes per run, >= 1")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="preset override")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/arm_learning.json)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error(f"--runs {args.runs}: expected an integer >= 1")
    if args.episodes < 1:
        ap.error(f"--episodes {args.episodes}: expected an integer >= 1")
    from jaxrobo.core.config import parse_overrides

    spec = resolve(ENV_ID, overrides={"eval_episodes": 0, **parse_overrides(args.set)})
    env, target = spec.env, spec.env.learning_target
    seeds = list(range(args.seed_base, args.seed_base + args.runs))
    runs = train_population(spec, seeds)
    train_s = runs.seconds  # compile included
    q = runs.runner.agent.q  # [runs, n_tables, S, A]; one shared table per run with the default preset
    disc = runs.trainer.disc

    def outcome(last) -> dict[str, jax.Array]:
        return {"success": last.task.arrived.mean(), "mean_steps": last.steps.mean()}

    def greedy(table):
        return outcome(rollout(env, greedy_policy(table, disc), jax.random.key(EVAL_SEED), args.episodes)["last"])

    # Every run's tables (one with the default preset), evaluated in one compiled, vmapped rollout.
    per_run = jax.tree.map(np.asarray, jax.jit(jax.vmap(greedy))(q))
    rand = jax.tree.map(float, jax.jit(lambda k: outcome(
        rollout(env, random_policy(env.num_actions), k, args.episodes)["last"]))(jax.random.key(EVAL_SEED)))
    success = [round(float(x), 4) for x in per_run["success"]]
    median = float(np.median(per_run["success"]))
    out = {"env": ENV_ID, "device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
           "runs": args.runs, "n_envs": spec.config.n_envs, "nepisodes": spec.config.nepisodes,
           "shared_table": spec.config.shared_table, "eval_episodes": args.episodes,
           "train_seconds": round(train_s, 2),
           "success_per_run": success,
           "mean_steps_per_run": [round(float(x), 1) for x in per_run["mean_steps"]],
           "median_success": round(median, 4), "min_success": min(success), "max_success": max(success),
           "seeds": seeds,
           "worst_seeds": [{"seed": seeds[i], "success": success[i]}
                           for i in np.argsort(per_run["success"], kind="stable")[:5]],
           "target": target.description, "median_meets_target": bool(median >= target.threshold),
           "random_policy": {k: round(v, 4) for k, v in rand.items()}, "overrides": args.set}
    print(json.dumps(out, indent=2))
    print(f"MEDIAN {median:.3f} (worst {min(success):.3f}); WORST seeds: "
          + ", ".join(f"seed {w['seed']} {w['success']:.3f}" for w in out["worst_seeds"]))
    _common.write_json(out, args.out, "arm_learning.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
