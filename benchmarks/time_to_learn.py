"""Wall time until the greedy policy meets its learning target: jaxrobo vs the seed-style loop.

Targets: cartpole - mean greedy episode length >= 500 steps over 100 evaluation episodes (episodes capped at
1000 steps, the seed's timestep_limit); quadcopter goto (when registered and exposing a success measure) -
>= 80 % of greedy episodes succeed.

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
import json
import os
import random
import sys
import time
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402

CARTPOLE_TARGET = 500.0
GOTO_ID = "QuadcopterGoto-v1"


def jaxrobo_cartpole(args) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxrobo.run import resolve
    from jaxrobo.train import Trainer

    spec = resolve("CartPoleStayUp-v0", "default", {"n_envs": args.n_envs, "chunk_steps": args.chunk_steps,
                                                    "seed": args.seed}, agent=args.agent)
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
    chunk = jax.jit(trainer.run_chunk, donate_argnums=0).lower(runner, ap, ep).compile()
    ev = jax.jit(evaluate).lower(runner, jax.random.key(0)).compile()
    jax.block_until_ready(runner)
    compile_s = time.perf_counter() - t0
    train_s, evals, best, chunks = 0.0, [], 0.0, 0
    met = False
    while train_s < args.budget and chunks < trainer.max_chunks():
        t = time.perf_counter()
        for _ in range(args.eval_every):
            runner = chunk(runner, ap, ep)
        jax.block_until_ready(runner)
        train_s += time.perf_counter() - t
        chunks += args.eval_every
        scores = [float(x) for x in ev(runner, jax.random.key(1000 + chunks))]
        best = max(scores)
        steps = int(np.asarray(runner.env_steps, np.int64).sum())
        evals.append({"train_seconds": train_s, "env_steps": steps, "best_mean_length": best,
                      "episodes_min": int(runner.episode.min())})
        print(f"  jaxrobo: {train_s:6.1f} s, {steps:,} steps, best greedy mean length {best:.0f}", flush=True)
        if best >= CARTPOLE_TARGET:
            met = True
            break
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


def goto_row() -> dict[str, Any]:
    import jaxrobo

    if GOTO_ID not in jaxrobo.registered():
        return {"side": "jaxrobo", "env": GOTO_ID, "status": "skipped", "reason": f"{GOTO_ID} is not registered"}
    env = jaxrobo.make(GOTO_ID)
    if not callable(getattr(env, "success", None)):
        return {"side": "jaxrobo", "env": GOTO_ID, "status": "skipped",
                "reason": "the goto task exposes no success measure (env.success(state, params)) yet"}
    return {"side": "jaxrobo", "env": GOTO_ID, "status": "skipped",
            "reason": "success-rate evaluation for the goto task is not wired into this script yet"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--agent", default="qlearn")
    p.add_argument("--n-envs", type=int, default=64, help="independent jaxrobo tables trained at once")
    p.add_argument("--chunk-steps", type=int, default=1000)
    p.add_argument("--eval-every", type=int, default=5, help="jaxrobo chunks between evaluations")
    p.add_argument("--eval-tables", type=int, default=4, help="jaxrobo tables evaluated (best recent returns)")
    p.add_argument("--seed-eval-every", type=int, default=500, help="seed-loop episodes between evaluations")
    p.add_argument("--budget", type=float, default=120.0, help="training seconds allowed per side")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip-seed-loop", action="store_true")
    p.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/time_to_learn.json)")
    args = p.parse_args(argv)
    for flag in ("n_envs", "chunk_steps", "eval_every", "eval_tables", "seed_eval_every"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} must be >= 1")
    _common.select_device(args.device)
    import jax

    from jaxrobo.cache import enable_compilation_cache

    enable_compilation_cache()
    print(f"time to learn on {jax.devices()[0].device_kind}; budget {args.budget:.0f} s per side", flush=True)
    rows = [jaxrobo_cartpole(args)]
    try:
        import gymnasium  # noqa: F401

        if not args.skip_seed_loop:
            rows.append(seed_cartpole(args))
    except ImportError:
        rows.append({"side": "seed-loop", "status": "skipped", "reason": "gymnasium is not installed"})
    rows.append(goto_row())
    print()
    for r in rows:
        if r.get("status") == "skipped":
            print(f"{r['side']:10s} {r['env']}: skipped ({r['reason']})")
            continue
        when = f"{r['seconds_to_target']:.1f} s" if r["met"] else f"not met in {r['train_seconds']:.0f} s"
        extra = f" (+ compile {r['compile_seconds']:.1f} s)" if "compile_seconds" in r else ""
        print(f"{r['side']:10s} {r['env']}: target {when}{extra}; best greedy mean length {r['best_mean_length']:.0f}")
    path = args.out or os.path.join(_common.ROOT, "benchmarks", "results", _common.device_name(), "time_to_learn.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"device": jax.devices()[0].device_kind, "argv": sys.argv, "rows": rows}, f, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
