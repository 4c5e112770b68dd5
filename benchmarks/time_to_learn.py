"""Wall time until the greedy policy meets its learning target: jaxrobo vs the seed-style loop.

Targets: cartpole - mean greedy episode length >= 500 steps over 100 evaluation episodes (episodes capped at
1000 steps, the seed's timestep_limit); quadcopter goto - >= 80 % of 100 greedy episodes arrive at their
random goal (``--goto-runs`` runs train side by side; see :func:`goto_row`). The goto task has no seed-style
side: the seed flew its drone in Gazebo, which nothing here can run.

jaxrobo trains ``--n-envs`` independent tables at once (the default preset) chunk by chunk; after every
``--eval-every`` chunks it evaluates the ``--eval-tables`` tables with the best recent returns (100 greedy
episodes each) and stops when one meets the target. The seed-style loop (dict Q-learning in plain Python over
Gymnasium ``CartPole-v1``, its time limit raised to 1000 steps) is evaluated the same way every
``--seed-eval-every`` episodes. Times exclude the evaluations; compile time is reported separately.

    python benchmarks/time_to_learn.py                      # CPU: each side gets --budget seconds
    python benchmarks/time_to_learn.py --device gpu --n-envs 4096 --budget 120
"""
from __future__ import annotations

import argparse
import os
import random
import sys
import time
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402

CARTPOLE_TARGET = 500.0
GOTO_ID = "QuadcopterGoto-v1"
GOTO_TARGET = 0.8  # share of greedy episodes that arrive at the goal


def train_until(runner, chunk, score, target, args, max_chunks, label):
    """Run ``--eval-every`` chunks at a time (the host driver's loop, :func:`jaxrobo.training.driver.run_chunks`, with
    nothing read back between chunks) until ``score`` reaches ``target``, ``--budget`` seconds of training pass
    or the run ends; only the chunks are timed (each stretch waited for with ``block_until_ready``).
    ``score(runner, chunks) -> (value, record, text)``. Returns the runner, the training seconds, the evaluation
    records, the last score and whether it met."""
    import numpy as np

    from jaxrobo.training import driver

    train_s, evals, best, chunks, met = 0.0, [], 0.0, 0, False
    while train_s < args.budget and chunks < max_chunks:
        stretch = driver.run_chunks(chunk, runner, chunks + args.eval_every, start_chunk=chunks)
        runner = stretch.carry
        train_s += stretch.seconds
        chunks = stretch.chunks_done
        best, record, text = score(runner, chunks)
        steps = int(np.asarray(runner.env_steps, np.int64).sum())
        evals.append({"train_seconds": train_s, "env_steps": steps, **record,
                      "episodes_min": int(runner.episode.min())})
        print(f"  {label}: {train_s:6.1f} s, {steps:,} steps, {text}", flush=True)
        if best >= target:
            met = True
            break
    return runner, train_s, evals, best, met


def jaxrobo_cartpole(args) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from jaxrobo.training import driver
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    overrides = {"n_envs": args.n_envs, "chunk_steps": args.chunk_steps, "seed": args.seed}
    if args.backend:
        overrides["backend"] = args.backend
    spec = resolve("CartPoleStayUp-v0", "default", overrides, agent=args.agent)
    trainer = Trainer(spec.env, spec.config)
    ap, ep = spec.agent_params, spec.env.default_params
    k = min(args.eval_tables, args.n_envs)

    def evaluate(runner, key):
        last = jnp.clip(runner.episode - 1, 0, runner.returns.shape[1] - 1)
        recent = jnp.take_along_axis(runner.returns, last[:, None], axis=1)[:, 0]
        top = jnp.argsort(-recent)[:k]
        tables = jax.tree.map(lambda x: x[top], runner.agent)
        _, lengths = jax.vmap(trainer.evaluate, in_axes=(0, 0, None, None))(
            jax.random.split(key, k), tables, 100, ep)
        return lengths.astype(jnp.float32).mean(axis=1)

    t0 = time.perf_counter()
    runner = jax.jit(trainer.init)(jax.random.key(args.seed), ap, ep)
    chunk = driver.compiled_chunk(trainer, runner, ap, ep)  # as ``jaxrobo train`` compiles it
    ev = jax.jit(evaluate).lower(runner, jax.random.key(0)).compile()
    jax.block_until_ready(runner)
    compile_s = time.perf_counter() - t0

    def score(runner, chunks):
        best = max(float(x) for x in ev(runner, jax.random.key(1000 + chunks)))
        return best, {"best_mean_length": best}, f"best greedy mean length {best:.0f}"

    runner, train_s, evals, best, met = train_until(runner, lambda r: chunk(r, ap, ep), score, CARTPOLE_TARGET,
                                                    args, trainer.max_chunks(), "jaxrobo")
    return {"side": "jaxrobo", "env": "CartPoleStayUp-v0", "agent": args.agent, "n_envs": args.n_envs,
            "target": f"mean greedy length >= {CARTPOLE_TARGET:.0f} over 100 episodes (best of {k} tables)",
            "met": met, "seconds_to_target": train_s if met else None, "compile_seconds": compile_s,
            "train_seconds": train_s, "best_mean_length": best, "evaluations": evals}


def seed_cartpole(args) -> dict[str, Any]:
    env = _common.make_gym_cartpole(max_episode_steps=1000)
    eval_env = _common.make_gym_cartpole(max_episode_steps=1000)
    agent = _common.DictQLearn(env.action_space.n, 0.1, 0.5, 0.9, random.Random(args.seed))
    train_s, steps, episodes, best, met, evals = 0.0, 0, 0, 0.0, False, []
    top = 0.0
    while train_s < args.budget:
        out = _common.seed_loop(env, agent, args.seed_eval_every, 1000, seed=args.seed + episodes)
        train_s += out["seconds"]
        steps += out["steps"]
        episodes += args.seed_eval_every
        best = _common.greedy_eval(eval_env, agent, 100, 1000)
        top = max(top, best)
        evals.append({"train_seconds": train_s, "env_steps": steps, "episodes": episodes, "mean_length": best})
        if len(evals) % 10 == 1 or best >= CARTPOLE_TARGET:
            print(f"  seed-loop: {train_s:6.1f} s, {steps:,} steps, {episodes} episodes, greedy mean length "
                  f"{best:.0f}", flush=True)
        if best >= CARTPOLE_TARGET:
            met = True
            break
    return {"side": "seed-loop", "env": "Gymnasium CartPole-v1 (limit 1000)", "agent": "dict QLearn (seed rules)",
            "target": f"mean greedy length >= {CARTPOLE_TARGET:.0f} over 100 episodes", "met": met,
            "seconds_to_target": train_s if met else None, "train_seconds": train_s, "best_mean_length": top,
            "evaluations": evals}


def goto_row(args) -> dict[str, Any]:
    """QuadcopterGoto-v1: ``--goto-runs`` default-preset runs train side by side (one vmapped computation); after
    every ``--eval-every`` chunks each run's table flies 100 greedy episodes to random goals, and the clock stops
    when the best run arrives in >= 80 % of them. That table is then flown on 200 fresh goals, so the reported
    rate is not the maximum of noisy estimates."""
    import jax
    import numpy as np

    import jaxrobo
    from _population import compiled_population
    from jaxrobo.task.rollout import greedy_policy, rollout
    from jaxrobo.training.run import resolve

    if GOTO_ID not in jaxrobo.registered():
        return {"side": "jaxrobo", "env": GOTO_ID, "status": "skipped", "reason": f"{GOTO_ID} is not registered"}
    spec = resolve(GOTO_ID, overrides={"eval_episodes": 0})
    env, ep = spec.env, spec.env.default_params
    runs = args.goto_runs

    t0 = time.perf_counter()
    # The runs' chunk vmapped, compiled as the driver compiles the single-run one (benchmarks/_population.py).
    trainer, runner, chunk = compiled_population(spec, [args.seed + i for i in range(runs)])

    def success(table, key, n):
        return rollout(env, greedy_policy(table, trainer.disc), key, n, params=ep)["last"].task.arrived.mean()

    select = jax.jit(jax.vmap(lambda t, k: success(t, k, 100))).lower(
        runner.agent.q, jax.random.split(jax.random.key(0), runs)).compile()
    compile_s = time.perf_counter() - t0
    last = {}

    def score(runner, chunks):
        last["rates"] = rates = np.asarray(select(runner.agent.q,
                                                  jax.random.split(jax.random.key(5000 + chunks), runs)))
        best = float(rates.max())
        return best, {"best_success": best, "mean_success": float(rates.mean())}, \
            f"best greedy success {best:.2f} (mean over {runs} runs {rates.mean():.2f})"

    runner, train_s, evals, best, met = train_until(runner, chunk, score, GOTO_TARGET, args,
                                                    trainer.max_chunks(), "goto   ")
    rates = last["rates"] if "rates" in last else np.asarray(  # no chunk ran (--budget 0): untrained tables
        select(runner.agent.q, jax.random.split(jax.random.key(5000), runs)))
    chosen = int(np.argmax(rates))
    fresh = float(jax.jit(lambda t, k: success(t, k, 200))(runner.agent.q[chosen], jax.random.key(123_456)))
    print(f"  goto:    selected run {chosen}: success {fresh:.2f} on 200 fresh goals", flush=True)
    return {"side": "jaxrobo", "env": GOTO_ID, "agent": spec.config.agent, "runs": runs,
            "n_envs": spec.config.n_envs, "target": f"greedy success >= {GOTO_TARGET:.0%} over 100 episodes "
            f"(best of {runs} runs), then re-flown on 200 fresh goals", "met": met,
            "seconds_to_target": train_s if met else None, "compile_seconds": compile_s, "train_seconds": train_s,
            "best_success": best, "selected_fresh_success": fresh, "evaluations": evals}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--agent", default="qlearn")
    p.add_argument("--backend", default=None, help="cart-pole physics backend (default: the env's, mjx)")
    p.add_argument("--n-envs", type=int, default=64, help="independent jaxrobo tables trained at once")
    p.add_argument("--chunk-steps", type=int, default=1000)
    p.add_argument("--eval-every", type=int, default=5, help="jaxrobo chunks between evaluations")
    p.add_argument("--eval-tables", type=int, default=4, help="jaxrobo tables evaluated (best recent returns)")
    p.add_argument("--seed-eval-every", type=int, default=500, help="seed-loop episodes between evaluations")
    p.add_argument("--budget", type=float, default=120.0, help="training seconds allowed per side")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip-seed-loop", action="store_true")
    p.add_argument("--goto-runs", type=int, default=None,
                   help="QuadcopterGoto-v1 runs trained side by side (default: 32 on a GPU, 8 on a CPU; 0 skips)")
    p.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/time_to_learn.json)")
    args = p.parse_args(argv)
    for flag in ("n_envs", "chunk_steps", "eval_every", "eval_tables", "seed_eval_every"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} must be >= 1")
    _common.select_device(args.device)
    import jax

    from jaxrobo.speed.cache import enable_compilation_cache

    enable_compilation_cache()
    if args.goto_runs is None:
        args.goto_runs = 32 if jax.default_backend() == "gpu" else 8
    if args.goto_runs < 0:
        p.error("--goto-runs must be >= 0")
    print(f"time to learn on {jax.devices()[0].device_kind}; budget {args.budget:.0f} s per side", flush=True)
    rows = [jaxrobo_cartpole(args)]
    try:
        import gymnasium  # noqa: F401

        if not args.skip_seed_loop:
            rows.append(seed_cartpole(args))
    except ImportError:
        rows.append({"side": "seed-loop", "status": "skipped", "reason": "gymnasium is not installed"})
    if args.goto_runs:
        rows.append(goto_row(args))
    else:
        rows.append({"side": "jaxrobo", "env": GOTO_ID, "status": "skipped", "reason": "--goto-runs 0"})
    print()
    for r in rows:
        if r.get("status") == "skipped":
            print(f"{r['side']:10s} {r['env']}: skipped ({r['reason']})")
            continue
        when = f"{r['seconds_to_target']:.1f} s" if r["met"] else f"not met in {r['train_seconds']:.0f} s"
        extra = f" (+ compile {r['compile_seconds']:.1f} s)" if "compile_seconds" in r else ""
        score = (f"best greedy mean length {r['best_mean_length']:.0f}" if "best_mean_length" in r else
                 f"best greedy success {r['best_success']:.2f}, selected run on fresh goals "
                 f"{r['selected_fresh_success']:.2f}")
        print(f"{r['side']:10s} {r['env']}: target {when}{extra}; {score}")
    path = _common.write_json({"device": jax.devices()[0].device_kind, "argv": sys.argv, "rows": rows}, args.out,
                              "time_to_learn.json")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
