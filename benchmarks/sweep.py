"""Many independent Q-learning runs of the seed's cartpole experiment in ONE sweep call (issue 5 target).

Target on an H100: 1,000 runs of 1,000 episodes of at most 1,000 steps each in under 60 s. The runs are a
grid of ``--configs`` learning rates × seeds, one table per run, trained by :func:`jaxrobo.training.sweep.run_sweep`
as one vmapped program (sharded over every local device when there are several). Reported: the wall time of
the whole call (compile included), the run time alone, env steps per second and the best learning rate.

    python benchmarks/sweep.py                                   # CPU-sized: 8 runs × 20 episodes
    python benchmarks/sweep.py --device gpu --runs 1000 --nepisodes 1000
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--env", default="CartPoleStayUp-v0")
    p.add_argument("--preset", default="default", help="default (textbook learner) or seed (seed_compat, round)")
    p.add_argument("--backend", default=None, help="cart-pole physics backend (default: the env's, mjx)")
    p.add_argument("--runs", type=int, default=None, help="independent runs (default: 1000 on GPU, 8 on CPU)")
    p.add_argument("--configs", type=int, default=4, help="learning rates in the grid (runs = configs × seeds)")
    p.add_argument("--nepisodes", type=int, default=None, help="episodes per run (default: 1000 GPU, 20 CPU)")
    p.add_argument("--nsteps", type=int, default=1000, help="step cap per episode")
    p.add_argument("--chunk-steps", type=int, default=1000)
    p.add_argument("--eval-episodes", type=int, default=0, help="greedy episodes per run after training")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="stop training after this many seconds and report how far the runs got")
    p.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/sweep.json)")
    args = p.parse_args(argv)
    _common.select_device(args.device)
    import jax
    import numpy as np

    from jaxrobo.speed import sharding
    from jaxrobo.speed.cache import enable_compilation_cache
    from jaxrobo.core.config import ConfigError
    from jaxrobo.training.sweep import run_sweep

    enable_compilation_cache()
    gpu = jax.default_backend() == "gpu"
    runs = args.runs or (1000 if gpu else 8)
    nepisodes = args.nepisodes or (1000 if gpu else 20)
    if args.configs < 1 or runs % args.configs:
        p.error(f"--runs {runs} must be a positive multiple of --configs {args.configs}")
    seeds = list(range(runs // args.configs))
    alphas = [round(float(a), 3) for a in np.linspace(0.1, 0.7, args.configs)] if args.configs > 1 else [0.5]
    points = [{"alpha": a} for a in alphas]
    overrides = {"n_envs": 1, "nepisodes": nepisodes, "nsteps": args.nsteps, "chunk_steps": args.chunk_steps}
    if args.backend:
        overrides["backend"] = args.backend
    mesh = sharding.make_mesh() if jax.device_count() > 1 else None
    print(f"{runs} runs ({len(points)} alphas × {len(seeds)} seeds) of {nepisodes} episodes ≤ {args.nsteps} steps, "
          f"{args.env} preset {args.preset}, on {jax.device_count()} × {jax.devices()[0].device_kind}", flush=True)
    t0 = time.perf_counter()
    try:
        result = run_sweep(args.env, points, seeds, args.preset, "qlearn", overrides, mesh, args.eval_episodes,
                           log=lambda m: print(m, flush=True), max_seconds=args.max_seconds)
    except ConfigError as err:
        print(f"benchmarks/sweep.py: {err}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - t0
    g = result.groups[0]
    steps = result.env_steps
    best = result.best("final_return")
    out = {"device": jax.devices()[0].device_kind, "device_count": jax.device_count(), "env": args.env,
           "backend": args.backend or "default",
           "preset": args.preset, "runs": runs, "nepisodes": nepisodes, "nsteps": args.nsteps, "alphas": alphas,
           "wall_seconds": wall, "compile_seconds": g["compile_seconds"], "run_seconds": g["run_seconds"],
           "env_steps": steps, "env_steps_per_second_run": steps / g["run_seconds"],
           "env_steps_per_second_wall": steps / wall, "best": best,
           "mean_final_return": float(np.mean([r["final_return"] for r in result.rows])),
           "complete": g["complete"], "episodes_done_min": int(min(r["episodes_done"] for r in result.rows)),
           "episodes_done_mean": float(np.mean([r["episodes_done"] for r in result.rows])),
           "target": "1,000 runs × 1,000 episodes ≤ 1,000 steps in < 60 s (H100)", "argv": sys.argv}
    print(f"{runs} runs: {steps:,} env steps; one sweep call {wall:.1f} s (compile {g['compile_seconds']:.1f} s, "
          f"run {g['run_seconds']:.1f} s) → {steps / g['run_seconds']:,.0f} steps/s while running")
    if not g["complete"]:
        print(f"stopped after --max-seconds {args.max_seconds:g}: episodes done per run min "
              f"{out['episodes_done_min']}, mean {out['episodes_done_mean']:.0f} of {nepisodes}")
    print(f"best alpha {best['alpha']} (mean return of the last 100 episodes {best['mean']:.1f} ± {best['std']:.1f})")
    if runs >= 1000 and nepisodes >= 1000 and g["complete"]:
        print(f"target < 60 s: {'met' if wall < 60 else 'missed'}")
    path = _common.write_json(out, args.out, "sweep.json", default=str)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
