"""Does QuadcopterGoto-v1 learn? Train several independent runs at once, select, then measure on fresh goals.

Each run is the default preset (one table shared by ``n_envs`` environments); ``--runs`` of them train side by
side as one vmapped computation, each from its own seed. Every trained table flies ``--select-episodes``
greedy episodes (random goals, obstacles present) and the best is then flown on ``--episodes`` *fresh*
episodes, so the reported rate is not the maximum of noisy estimates. The random policy's rate, and every
run's selection-set rate, are reported beside it.

    python benchmarks/goto_learning.py                    # CPU-sized
    python benchmarks/goto_learning.py --runs 32          # GPU
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxrobo import driver  # noqa: E402
from jaxrobo.rollout import greedy_policy, random_policy, rollout  # noqa: E402
from jaxrobo.run import resolve  # noqa: E402
from jaxrobo.trainer import Trainer  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4, help="independent training runs (seeds 0..runs-1)")
    ap.add_argument("--select-episodes", type=int, default=100)
    ap.add_argument("--episodes", type=int, default=200, help="fresh evaluation episodes of the selected table")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="preset override")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/goto_learning.json)")
    args = ap.parse_args(argv)
    from jaxrobo.config import parse_overrides

    spec = resolve("QuadcopterGoto-v1", overrides={"eval_episodes": 0, **parse_overrides(args.set)})
    trainer = Trainer(spec.env, spec.config)
    keys = jnp.stack([jax.random.key(s) for s in range(args.runs)])
    t0 = time.perf_counter()
    ap_, ep = spec.agent_params, spec.env.default_params
    runner = jax.jit(jax.vmap(trainer.init, in_axes=(0, None, None)))(keys, ap_, ep)
    plan = trainer.plan  # the runs' chunk vmapped, compiled and looped by the host driver as jaxrobo train's
    chunk = driver.compile_under(plan, jax.jit(jax.vmap(trainer.run_chunk, in_axes=(0, None, None)), donate_argnums=0,
                                               compiler_options=plan.xla_options), runner, ap_, ep)
    runner = driver.run_chunks(lambda r: chunk(r, ap_, ep), runner, trainer.max_chunks(),
                               read=driver.compiled_progress(runner), total=spec.config.nepisodes).carry
    train_s = time.perf_counter() - t0  # compile included, as before
    q = np.asarray(runner.agent.q)  # [runs, n_tables, S, A] (shared table per run)
    env, disc = spec.env, trainer.disc

    def outcome(last) -> dict[str, jax.Array]:
        arrived, crashed = last.task.arrived, last.task.crashed
        return {"success": arrived.mean(), "failure": crashed.mean(), "timeout": (~arrived & ~crashed).mean(),
                "mean_steps": last.steps.mean()}

    # One compiled evaluation for every table: the table is an argument, not a constant.
    greedy_rate = jax.jit(lambda table, k, n: outcome(rollout(env, greedy_policy(table, disc), k, n)["last"]),
                          static_argnums=2)
    as_float = lambda d: {k: round(float(v), 4) for k, v in d.items()}  # noqa: E731
    select = [as_float(greedy_rate(q[i], jax.random.key(10_000 + i), args.select_episodes)) for i in range(args.runs)]
    best = int(np.argmax([s["success"] for s in select]))
    fresh = as_float(greedy_rate(q[best], jax.random.key(123_456), args.episodes))
    rand = as_float(jax.jit(lambda k: outcome(rollout(env, random_policy(env.num_actions), k, args.episodes)["last"]))(
        jax.random.key(123_456)))
    out = {"device": jax.devices()[0].device_kind, "runs": args.runs, "n_envs": spec.config.n_envs,
           "nepisodes": spec.config.nepisodes, "train_seconds": round(train_s, 2),
           "selection_success_per_run": [round(s["success"], 3) for s in select],
           "mean_selection_success": float(np.mean([s["success"] for s in select])),
           "selected_run": best, "selected_fresh": fresh, "random_fresh": rand}
    print(json.dumps(out, indent=2))
    path = args.out or os.path.join(_common.ROOT, "benchmarks", "results", _common.device_name(), "goto_learning.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
