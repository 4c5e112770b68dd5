"""What the Gymnasium adapter costs: single-env step latency, and the vector env against Gymnasium's SyncVectorEnv.

    python benchmarks/adapter_latency.py                       # CartPoleStayUp-v0, N = 1, 16, 256, on CPU
    python benchmarks/adapter_latency.py --env QuadcopterGoto-v1 --n-envs 1,16

Rows:

* ``single``: ``JaxroboEnv.step`` (one jitted call + one device→host transfer), and the same through
  ``gymnasium.make`` (its PassiveEnvChecker, OrderEnforcing and TimeLimit wrappers); per-step latency after
  compilation (median and 90th percentile over ``--steps`` steps, resetting when an episode ends).
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
        lat = f"{r['median_us']:.0f} µs (median)" if r["kind"] == "single" else f"{r['ms_per_call']:.3f} ms"
        ratio = f"{r['x_vector_over_sync']:.1f}" if "x_vector_over_sync" in r else ""
        print(f"| {r['api']} | {r['n_envs']} | {lat} | {r['steps_per_s']:,.0f} | {ratio} |")

    out_dir = args.out or os.path.join(_common.ROOT, "benchmarks", "results", "cpu" if args.device == "cpu" else device)
    meta = {"env": args.env, "device": device, "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__, "gymnasium": gym.__version__,
            "steps": args.steps, "vector_seconds": args.vector_seconds, "compile_cache": cache,
            "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
            "command": " ".join([os.path.basename(sys.executable)] + sys.argv)}
    path = _common.write_json({"meta": meta, "rows": rows}, os.path.join(out_dir, "adapter_latency.json"))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
