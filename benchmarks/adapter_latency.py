"""What the Gymnasium adapter costs: single-env step latency, and the vector env against Gymnasium's SyncVectorEnv.

    python benchmarks/adapter_latency.py                       # CartPoleStayUp-v0, N = 1, 16, 256, on CPU
    python benchmarks/adapter_latency.py --env QuadcopterGoto-v1 --n-envs 1,16

Rows:

* ``single``: ``JaxroboEnv.step`` (one jitted call + one device→host transfer), and the same through
  ``gymnasium.make`` (its PassiveEnvChecker, OrderEnforcing and TimeLimit wrappers); per-step latency after
  compilation (median and 90th percentile over ``--steps`` steps, resetting when an episode ends).
* ``episodes``: steps per second of one env through ``gymnasium.make`` with random actions, resets included, for
  the adapter's engines (``engine="jax"``; ``engine="numpy"``, the task's host step, on each backend it runs) beside
  Gymnasium's own ``CartPole-v1``, in one process. The rows alternate over ``--rounds`` rounds and the median of
  each is reported (a shared machine's load moves any single run).
* ``vector`` vs ``sync``: env-steps per second of ``gymnasium.make_vec(..., num_envs=N)`` (the adapter's
  vmapped ``JaxroboVectorEnv``) and of ``make_vec(..., vectorization_mode="sync")`` (Gymnasium's
  ``SyncVectorEnv`` of N single adapters), random actions, next-step autoreset in both.

Compile time is measured separately (first call) and never counted in a timed row. Output: a table on stdout and
``benchmarks/results/cpu/adapter_latency.json`` (``--out`` to change).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="CartPoleStayUp-v0", help="jaxrobo id")
    p.add_argument("--n-envs", default="1,16,256", help="comma list of vector sizes")
    p.add_argument("--steps", type=int, default=2000, help="timed single-env steps")
    p.add_argument("--episode-steps", type=int, default=20000,
                   help="steps per round of each episodes row (a tenth of it for engine='jax')")
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds of the episodes rows (median reported)")
    p.add_argument("--vector-seconds", type=float, default=3.0, help="time budget per vector row (s)")
    p.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    p.add_argument("--out", default=None, help="output folder (default benchmarks/results/cpu)")
    p.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    return p.parse_args(argv)


def _quiet_make(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*is out of date.*", category=DeprecationWarning)
        return fn(*args, **kw)


def single_latency(env: Any, steps: int) -> dict[str, float]:
    """Per-step seconds of ``env.step`` after a compile-and-warm-up episode."""
    import numpy as np

    rng = np.random.default_rng(0)
    n = env.action_space.n
    t0 = time.perf_counter()
    env.reset(seed=0)
    env.step(0)
    first = time.perf_counter() - t0
    env.reset(seed=1)
    times = np.empty(steps)
    actions = rng.integers(n, size=steps)
    for i in range(steps):
        t = time.perf_counter()
        _, _, term, trunc, _ = env.step(int(actions[i]))
        times[i] = time.perf_counter() - t
        if term or trunc:
            env.reset()
    return {"compile_and_first_s": first, "median_us": float(np.median(times) * 1e6),
            "p90_us": float(np.percentile(times, 90) * 1e6), "mean_us": float(times.mean() * 1e6),
            "steps_per_s": float(1.0 / times.mean())}


def episode_throughput(env: Any, steps: int, seed: int) -> float:
    """Steps per second of ``env`` over ``steps`` steps with random actions, resetting (unseeded) whenever an
    episode ends: what a single-env learner sees."""
    import numpy as np

    actions = np.random.default_rng(seed).integers(env.action_space.n, size=steps).tolist()
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - t0)


def episode_rows(env_id: str, steps: int, rounds: int) -> list[dict[str, Any]]:
    """The ``episodes`` rows: each engine of ``env_id`` (and backend of its host step) and ``CartPole-v1``, the
    rows alternating over ``rounds``, each warmed up (compiled) before the first."""
    import gymnasium as gym
    import numpy as np

    import jaxrobo

    task = jaxrobo.make(env_id)
    makers: dict[str, tuple[Any, int]] = {
        f"{env_id} engine=jax": (lambda: gym.make(f"jaxrobo/{env_id}"), max(1, steps // 10))}
    host_step = getattr(type(task), "host_step", None)
    if host_step is not None:
        for backend in host_step.backends:
            if host_step.unsupported(jaxrobo.make(env_id, backend=backend)) is not None:
                continue
            makers[f"{env_id} engine=numpy backend={backend}"] = (
                lambda b=backend: gym.make(f"jaxrobo/{env_id}", engine="numpy", backend=b), steps)
    makers["CartPole-v1 (Gymnasium)"] = (lambda: gym.make("CartPole-v1"), steps)
    envs = {name: _quiet_make(make) for name, (make, _) in makers.items()}
    for env in envs.values():
        episode_throughput(env, 200, seed=0)  # compile and warm up
    rates: dict[str, list[float]] = {name: [] for name in envs}
    for r in range(rounds):
        for name, env in envs.items():
            rates[name].append(episode_throughput(env, makers[name][1], seed=r))
    rows = []
    for name, env in envs.items():
        env.close()
        rows.append({"kind": "episodes", "api": name, "n_envs": 1, "steps": makers[name][1], "rounds": rounds,
                     "steps_per_s": float(np.median(rates[name])), "steps_per_s_rounds": rates[name]})
    return rows


def vector_throughput(venv: Any, budget: float) -> dict[str, float]:
    """Env-steps per second of a vector env with random actions, after one compile-and-warm-up step."""
    import numpy as np

    n = venv.num_envs
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    venv.reset(seed=0)
    venv.step(rng.integers(venv.single_action_space.n, size=n))
    first = time.perf_counter() - t0
    calls = 0
    t0 = time.perf_counter()
    while True:
        venv.step(rng.integers(venv.single_action_space.n, size=n))
        calls += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= budget and calls >= 5:
            break
    return {"compile_and_first_s": first, "calls": calls, "seconds": elapsed,
            "ms_per_call": 1e3 * elapsed / calls, "steps_per_s": n * calls / elapsed}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _common.select_device(args.device)
    import gymnasium as gym
    import jax

    import jaxrobo  # noqa: F401  (registers jaxrobo/<id>)
    from jaxrobo.speed.cache import enable_compilation_cache
    from jaxrobo.interop.gym_adapter import JaxroboEnv

    cache = None if args.no_cache else enable_compilation_cache()
    gid = f"jaxrobo/{args.env}"
    sizes = [int(x) for x in args.n_envs.split(",") if x.strip()]
    device = _common.device_name()
    print(f"adapter latency · {args.env} · {device} · jax {jax.__version__} · gymnasium {gym.__version__} · "
          f"compile cache {cache or 'off'}", flush=True)

    rows: list[dict[str, Any]] = []
    raw = JaxroboEnv(args.env)
    rows.append({"kind": "single", "api": "JaxroboEnv.step", "n_envs": 1, **single_latency(raw, args.steps)})
    made = _quiet_make(gym.make, gid)
    rows.append({"kind": "single", "api": "gymnasium.make(...).step", "n_envs": 1,
                 **single_latency(made, args.steps)})
    made.close()
    for r in rows:
        print(f"  {r['api']:<28} median {r['median_us']:8.1f} µs  p90 {r['p90_us']:8.1f} µs  "
              f"({r['steps_per_s']:,.0f} steps/s; compile+first {r['compile_and_first_s']:.1f} s)", flush=True)

    episodes = episode_rows(args.env, args.episode_steps, args.rounds)
    ref = next(r["steps_per_s"] for r in episodes if r["api"].startswith("CartPole-v1"))
    for r in episodes:
        r["x_over_cartpole_v1"] = r["steps_per_s"] / ref
        print(f"  {r['api']:<44} {r['steps_per_s']:>10,.0f} steps/s (median of {r['rounds']}; "
              f"x{r['x_over_cartpole_v1']:.2f} CartPole-v1)", flush=True)
    rows.extend(episodes)

    for n in sizes:
        ours = _quiet_make(gym.make_vec, gid, num_envs=n)
        a = vector_throughput(ours, args.vector_seconds)
        ours.close()
        sync = _quiet_make(gym.make_vec, gid, num_envs=n, vectorization_mode="sync")
        b = vector_throughput(sync, args.vector_seconds)
        sync.close()
        rows.append({"kind": "vector", "api": "make_vec (JaxroboVectorEnv)", "n_envs": n, **a})
        rows.append({"kind": "vector", "api": "make_vec sync (SyncVectorEnv)", "n_envs": n, **b,
                     "x_vector_over_sync": a["steps_per_s"] / b["steps_per_s"]})
        print(f"  N={n:<4} vector {a['steps_per_s']:>12,.0f} steps/s ({a['ms_per_call']:.3f} ms/step)   "
              f"sync {b['steps_per_s']:>10,.0f} steps/s ({b['ms_per_call']:.3f} ms/step)   "
              f"x{a['steps_per_s'] / b['steps_per_s']:.1f}", flush=True)

    print("\n| API | N | latency / step | env-steps/s | vector ÷ sync |\n| --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        if r["kind"] == "episodes":
            print(f"| {r['api']}, random actions, resets included | 1 | | {r['steps_per_s']:,.0f} "
                  f"(median of {r['rounds']}) | x{r['x_over_cartpole_v1']:.2f} CartPole-v1 |")
            continue
        lat = f"{r['median_us']:.0f} µs (median)" if r["kind"] == "single" else f"{r['ms_per_call']:.3f} ms"
        ratio = f"{r['x_vector_over_sync']:.1f}" if "x_vector_over_sync" in r else ""
        print(f"| {r['api']} | {r['n_envs']} | {lat} | {r['steps_per_s']:,.0f} | {ratio} |")

    out_dir = args.out or os.path.join(_common.ROOT, "benchmarks", "results", "cpu" if args.device == "cpu" else device)
    meta = {"env": args.env, "device": device, "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__, "gymnasium": gym.__version__,
            "steps": args.steps, "episode_steps": args.episode_steps, "rounds": args.rounds,
            "vector_seconds": args.vector_seconds, "compile_cache": cache,
            "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
            "command": " ".join([os.path.basename(sys.executable)] + sys.argv)}
    path = _common.write_json({"meta": meta, "rows": rows}, os.path.join(out_dir, "adapter_latency.json"))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
