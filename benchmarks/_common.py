"""Shared pieces of the benchmark scripts: device selection, honest timing, the peers and the seed-style loop.

Honest timing: every measured function is compiled (and its compile time recorded) before it is timed, run
once to warm up, then timed ``repeats`` times with ``block_until_ready``; the minimum is kept. Its output
depends on the whole final state (a reduction over every leaf), so XLA cannot drop any of the work.
"""
from __future__ import annotations

import math
import os
import random
import socket
import subprocess
import sys
import time
from typing import Any, Callable

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Training config overrides for a timed run: episodes without end, nothing recorded, no evaluation, so every
#: chunk does the same work and the carry holds only what training needs. "Without end": more episodes than any
#: timed run reaches, yet nepisodes x nsteps (1000) within the int32 step counters that resolve() checks.
TIMED_TRAINING = {"record_episodes": False, "nepisodes": 2_000_000, "eval_episodes": 0}
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def free_port() -> int:
    """A TCP port of localhost free now (a coordinator's, a ROS master's)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def git_commit(*paths: str) -> str:
    """The commit a script runs at, "+ uncommitted changes" where ``jaxrobo`` or ``paths`` (relative to the
    repository) differ from it; "unknown" outside a git checkout."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "jaxrobo", *paths)
    return commit + (" + uncommitted changes" if dirty else "")


def select_device(device: str | None) -> None:
    """Pin JAX to ``cpu`` or ``gpu`` (before jax is imported); None leaves JAX's own choice."""
    if device is None:
        return
    if "jax" in sys.modules:
        raise RuntimeError("select_device must run before jax is imported")
    os.environ["JAX_PLATFORMS"] = {"cpu": "cpu", "gpu": "cuda"}[device]


def device_name() -> str:
    """A folder-safe name of the device in use, e.g. ``cpu-2cores`` or ``NVIDIA-H100-80GB-HBM3``."""
    import jax

    d = jax.devices()[0]
    if d.platform == "cpu":
        return f"cpu-{os.cpu_count()}cores"
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in d.device_kind).strip("-")


def checksum(tree: Any) -> Any:
    """One float that depends on every leaf (keeps the whole computation alive)."""
    import jax
    import jax.numpy as jnp

    total = jnp.float32(0)
    for leaf in jax.tree.leaves(tree):
        if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        total = total + jnp.sum(jnp.asarray(leaf).astype(jnp.float32))
    return total


def tree_bytes(tree: Any) -> int:
    """Bytes of every array leaf (works on ``jax.eval_shape`` output too)."""
    import jax
    import numpy as np

    total = 0
    for leaf in jax.tree.leaves(tree):
        dtype = leaf.dtype
        if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
            total += int(np.prod(leaf.shape)) * 8
            continue
        total += int(np.prod(leaf.shape)) * np.dtype(dtype).itemsize
    return total


def time_carry(fn: Callable, carry: Any, *args: Any, repeats: int = 3,
               min_seconds: float = 0.0) -> tuple[float, Any]:
    """Seconds per call of ``carry = fn(carry, *args)``: the minimum over ``repeats`` samples, after one warm-up
    call; returns (s, carry).

    ``fn`` returns ``(carry, checksum)``; both are waited for at the end of each sample. A sample is as many
    back-to-back calls as fill ``min_seconds`` (judged from the warm-up call): a 20 ms call timed alone on a
    busy 2-core machine measures mostly dispatch and scheduling jitter.
    """
    import jax

    t0 = time.perf_counter()
    carry, check = fn(carry, *args)
    jax.block_until_ready((carry, check))
    calls = max(1, min(1000, math.ceil(min_seconds / max(time.perf_counter() - t0, 1e-6))))
    best = float("inf")
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        for _ in range(calls):
            carry, check = fn(carry, *args)
        jax.block_until_ready((carry, check))
        best = min(best, (time.perf_counter() - t0) / calls)
    return best, carry


def compile_timed(jitted: Callable, *args: Any, cache_dir: str | None = None) -> tuple[Callable, float, bool]:
    """AOT-compile; returns (compiled, seconds, from_cache). A compile that wrote no cache file was a hit."""
    return timed(lambda: jitted.lower(*args).compile(), cache_dir)


def timed(compile_fn: Callable[[], Callable], cache_dir: str | None = None) -> tuple[Callable, float, bool]:
    """``compile_fn()`` (e.g. :func:`jaxrobo.training.driver.compiled_chunk`, the chunk ``jaxrobo train`` runs), timed;
    returns (compiled, seconds, from_cache). A compile that wrote no cache file was a hit."""
    from jaxrobo.speed.cache import entries

    before = entries(cache_dir)
    t0 = time.perf_counter()
    compiled = compile_fn()
    seconds = time.perf_counter() - t0
    hit = cache_dir is not None and entries(cache_dir) == before
    return compiled, seconds, hit


def write_json(out: Any, path: str | None, name: str | None = None, default: Callable[[Any], Any] | None = None) -> str:
    """Write ``out`` as indented JSON to ``path``, or by default to ``benchmarks/results/<device>/<name>``
    (folders made as needed); returns the path written. ``default`` is :func:`json.dump`'s (e.g. ``str`` for rows
    that may hold values JSON has no type for)."""
    import json

    if path is None and name is None:
        raise ValueError("write_json needs a path or a default file name")
    path = path or os.path.join(ROOT, "benchmarks", "results", device_name(), name)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f, indent=2, default=default)
    return path


def device_memory() -> dict[str, int]:
    """Device memory statistics where the backend has them (GPU), else {}."""
    import jax

    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 - CPU backends have none
        return {}
    return {k: int(stats[k]) for k in ("bytes_in_use", "peak_bytes_in_use", "bytes_limit") if k in stats}


# ---- the seed-style loop (seed 001's QLearn and training loop, by the rules of ``seed_compat``) --------------------
class DictQLearn:
    """Tabular Q-learning over a dict keyed by (state string, action), with the seed's rules (``seed_compat`` in
    jaxrobo/tabular/learner.py).

    First update of an entry stores the reward itself; later ones move by alpha towards r + gamma max Q(s').
    Exploration: with probability epsilon, uniform noise of the table's magnitude is added to the action values
    before the argmax; ties are broken uniformly at random.
    """

    def __init__(self, n_actions: int, epsilon: float, alpha: float, gamma: float, rng: random.Random):
        self.q: dict[tuple[str, int], float] = {}
        self.actions = range(n_actions)
        self.epsilon, self.alpha, self.gamma = epsilon, alpha, gamma
        self.rng = rng

    def values(self, state: str) -> list[float]:
        return [self.q.get((state, a), 0.0) for a in self.actions]

    def choose(self, state: str, greedy: bool = False) -> int:
        vals = self.values(state)
        if not greedy and self.rng.random() < self.epsilon:
            mag = max(abs(min(vals)), abs(max(vals)))
            vals = [v + self.rng.random() * mag - 0.5 * mag for v in vals]
        top = max(vals)
        best = [a for a, v in zip(self.actions, vals) if v == top]
        return best[0] if len(best) == 1 else self.rng.choice(best)

    def learn(self, s: str, a: int, r: float, s2: str) -> None:
        old = self.q.get((s, a))
        if old is None:
            self.q[(s, a)] = r
        else:
            self.q[(s, a)] = old + self.alpha * (r + self.gamma * max(self.values(s2)) - old)


def state_key(obs: Any) -> str:
    """The seed's state: the observation rounded to 0.1, joined into one string."""
    return "".join(str(round(float(x), 1)) for x in obs)


def make_gym_cartpole(max_episode_steps: int | None = None) -> Any:
    import gymnasium as gym

    kw = {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}
    return gym.make("CartPole-v1", **kw)


def seed_loop(env: Any, agent: DictQLearn, nepisodes: int, nsteps: int, epsilon_discount: float = 0.999,
              epsilon_min: float = 0.05, seed: int = 0, max_steps: int | None = None,
              deadline: float | None = None) -> dict[str, Any]:
    """The seed's loop: per episode decay epsilon, reset, up to ``nsteps`` steps learning every step.

    Stops early after ``max_steps`` env steps in total or at wall-clock ``deadline``. Returns the step count,
    episode lengths and the time spent.
    """
    steps, lengths = 0, []
    t0 = time.perf_counter()
    for episode in range(nepisodes):
        if agent.epsilon > epsilon_min:
            agent.epsilon *= epsilon_discount
        obs, _ = env.reset(seed=seed + episode if episode == 0 else None)
        state = state_key(obs)
        for i in range(nsteps):
            action = agent.choose(state)
            obs, reward, terminated, truncated, _ = env.step(action)
            next_state = state_key(obs)
            agent.learn(state, action, float(reward), next_state)
            steps += 1
            if terminated or truncated:
                lengths.append(i + 1)
                break
            state = next_state
        else:
            lengths.append(nsteps)
        if (max_steps is not None and steps >= max_steps) or (deadline is not None and time.perf_counter() > deadline):
            break
    return {"steps": steps, "lengths": lengths, "seconds": time.perf_counter() - t0}


def greedy_eval(env: Any, agent: DictQLearn, episodes: int, horizon: int, seed: int = 10_000) -> float:
    """Mean length of greedy episodes (ties still random, as the seed's policy)."""
    total = 0
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        for i in range(horizon):
            obs, _, terminated, truncated, _ = env.step(agent.choose(state_key(obs), greedy=True))
            if terminated or truncated:
                break
        total += i + 1
    return total / episodes
