#!/usr/bin/env python
"""The seed's ``start_training.py``, modernised: one environment through ``gymnasium.make``, one tabular learner,
the episodes × steps loop in plain Python.

What changed from the seed (openai_ros, seed 001):

* ROS and Gazebo are gone: ``gymnasium.make("jaxrobo/CartPoleStayUp-v0")`` builds the MuJoCo MJX model, and
  ``import jaxrobo`` is what registers the ``jaxrobo/`` ids with Gymnasium.
* The parameters come from the shipped YAML files (environment and learner halves, the seed's split) through
  :func:`jaxrobo.training.run.resolve`, instead of the ROS parameter server; ``--set KEY=VALUE`` overrides any of them.
* ``gym.wrappers.Monitor`` no longer exists: results go to a run directory that ``jaxrobo plot`` reads
  (``config.yaml``, ``episodes.csv``, ``summary.json``, ``qtables.npz``).
* States are integer bins (:func:`jaxrobo.training.trainer.make_discretiser_for`); ``--preset seed`` reproduces the
  seed's rounding to 0.1 and its learner rules exactly.

This is the slow, classic path on purpose (one env, numpy ↔ JAX every step); ``jaxrobo train`` runs the same
experiment for thousands of environments in one compiled loop.

    python examples/start_training.py --env CartPoleStayUp-v0 --episodes 50
    python examples/start_training.py --env CartPoleStayUp-v0 --agent sarsa --preset seed --out runs/classic
    jaxrobo plot runs/classic
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import gymnasium as gym
import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import agents  # noqa: E402
import jaxrobo  # noqa: E402,F401  (registers the jaxrobo/<id> environments with Gymnasium)
from jaxrobo.tabular import learner as tabular  # noqa: E402
from jaxrobo.io import results  # noqa: E402
from jaxrobo.core.config import ConfigError, parse_overrides  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402
from jaxrobo.tabular.discretise import make_discretiser_for  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="CartPoleStayUp-v0", help="jaxrobo id (made as gymnasium 'jaxrobo/<id>')")
    p.add_argument("--agent", default=None, help="qlearn, sarsa, expected_sarsa or double_q (default: the preset's)")
    p.add_argument("--preset", default="default", help="preset of the agent YAML: default (learns) or seed")
    p.add_argument("--episodes", type=int, default=None, help="override nepisodes")
    p.add_argument("--steps", type=int, default=None, help="override nsteps (step cap per episode)")
    p.add_argument("--seed", type=int, default=None, help="random seed (env resets and the learner)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="any learner, loop or env parameter")
    p.add_argument("--out", default=None, help="run directory (default training_results/<env>_<agent>_classic_<time>)")
    p.add_argument("--quiet", action="store_true", help="no per-episode lines")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        overrides = parse_overrides(args.set or [])
        for key, value in (("nepisodes", args.episodes), ("nsteps", args.steps), ("seed", args.seed)):
            if value is not None:
                overrides[key] = value
        spec = resolve(args.env, args.preset, overrides, agent=args.agent)
    except ConfigError as err:
        print(f"start_training: {err}", file=sys.stderr)
        return 2
    cfg, hp = spec.config, spec.agent_params
    if cfg.shared_table:  # one environment has one table either way
        print("note: shared_table is moot with one environment; using its single table")

    # Create the Gymnasium environment (the seed's gym.make('CartPoleStayUp-v0')), with the preset's env values.
    with warnings.catch_warnings():  # Gymnasium calls -v0 "out of date" when a -v1 exists; ours is a variant
        warnings.filterwarnings("ignore", message=".*is out of date.*", category=DeprecationWarning)
        env = gym.make(f"jaxrobo/{spec.env_id}", **spec.env_overrides)
    out = args.out or os.path.join("training_results",
                                   f"{spec.env_id}_{cfg.agent}_classic_{time.strftime('%Y%m%d-%H%M%S')}")

    # The learner: pure functions over one table, each step jitted once.
    learner = agents.get(cfg.agent)
    disc = make_discretiser_for(spec.env, cfg)
    n_actions = int(env.action_space.n)
    agent = tabular.init(learner, disc.n_states, n_actions, cfg.seed_compat)
    act = jax.jit(lambda k, ag, s, eps: tabular.act(learner, k, ag, s, eps, cfg.seed_compat))
    learn = jax.jit(lambda k, ag, s, a, r, s2, a2, term, eps: tabular.learn(
        learner, k, ag, s, a, r, s2, a2, term, eps, hp, cfg.seed_compat))
    state_of = jax.jit(disc.__call__)
    key = jax.random.key(cfg.seed)

    returns = np.zeros(cfg.nepisodes, np.float32)
    lengths = np.zeros(cfg.nepisodes, np.int32)
    terminated_eps = np.zeros(cfg.nepisodes, bool)
    epsilons = np.zeros(cfg.nepisodes, np.float32)
    epsilon = np.float32(hp.epsilon)
    highest_reward = -np.inf
    start = time.time()
    print(f"{spec.env_id} · {cfg.agent} ({spec.preset}) · 1 env × {cfg.nepisodes} episodes ≤ {cfg.nsteps} steps "
          f"through gymnasium.make → {out}")

    for x in range(cfg.nepisodes):
        cumulated_reward = 0.0
        if epsilon > hp.epsilon_min:  # the seed: epsilon *= epsilon_discount while above 0.05
            epsilon = np.float32(epsilon * hp.epsilon_discount)
        observation, _ = env.reset(seed=cfg.seed if x == 0 else None)
        state = state_of(observation)
        key, k = jax.random.split(key)
        action = act(k, agent, state, epsilon)
        terminated = truncated = False
        i = 0
        for i in range(cfg.nsteps):
            # Execute the action in the environment and get feedback (classic API, numpy out).
            observation, reward, terminated, truncated, info = env.step(int(action))
            cumulated_reward += reward
            highest_reward = max(highest_reward, cumulated_reward)
            next_state = state_of(observation)
            key, k_act, k_learn = jax.random.split(key, 3)
            # Sarsa-type learners learn from the action they will take next; Q-learning picks after learning.
            next_action = act(k_act, agent, next_state, epsilon) if learner.on_policy else action
            agent = learn(k_learn, agent, state, action, reward, next_state, next_action, terminated, epsilon)
            if terminated or truncated:
                break
            state = next_state
            action = next_action if learner.on_policy else act(k_act, agent, next_state, epsilon)
        returns[x], lengths[x], terminated_eps[x], epsilons[x] = cumulated_reward, i + 1, terminated, epsilon
        if not args.quiet:
            m, s = divmod(int(time.time() - start), 60)
            h, m = divmod(m, 60)
            print(f"EP: {x + 1} - [alpha: {hp.alpha:.2f} - gamma: {hp.gamma:.2f} - epsilon: {epsilon:.2f}] - "
                  f"Reward: {cumulated_reward:g}     Time: {h}:{m:02d}:{s:02d}")
    env.close()
    seconds = time.time() - start

    # The seed's closing figures: parameters and highest reward, overall mean episode length, best 100 mean.
    best = np.sort(lengths)[-100:]
    print(f"\n|{cfg.nepisodes}|{hp.alpha}|{hp.gamma}|{hp.epsilon}*{hp.epsilon_discount}|{highest_reward:g}| PICTURE |")
    print(f"Overall score: {lengths.mean():0.2f}")
    print(f"Best 100 score: {best.mean():0.2f}")

    steps = int(lengths.sum())
    summary = {
        "env_id": spec.env_id, "agent": cfg.agent, "n_envs": 1, "nepisodes": cfg.nepisodes,
        "runner": "examples/start_training.py (gymnasium.make, one env)",
        "highest_reward_mean": float(returns.max()), "highest_reward_max": float(returns.max()),
        "overall_mean_length": float(lengths.mean()), "best_100_mean_length": float(best.mean()),
        "final_100_mean_return": float(returns[-100:].mean()), "env_steps": steps,
        "run_seconds": round(seconds, 3), "env_steps_per_second": round(steps / max(seconds, 1e-9), 1),
    }
    results.write_config(out, {**spec.to_dict(), "runner": "examples/start_training.py"})
    results.write_episodes(out, returns[None], lengths[None], terminated_eps[None], epsilons)
    results.write_tables(out, np.asarray(agent.q)[None], disc)
    results.write_summary(out, summary)
    print(f"results in {out} ({steps} steps in {seconds:.1f} s); plot them with: jaxrobo plot {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
