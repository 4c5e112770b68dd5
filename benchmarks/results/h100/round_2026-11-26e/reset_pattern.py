"""Per program of 32 lanes (CPU, the plain path, 8,192 envs, 200 episodes): how many steps have a reset, how many
more than the groups of four can take (block / 4), and lanes done per such step, for three of
randomisation_cost.py's variants. Run from the repository root: python benchmarks/results/h100/round_2026-11-26e/reset_pattern.py"""
import sys, numpy as np, json
sys.path.insert(0, "benchmarks")
import randomisation_cost as rc
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train
n, eps, block = 8192, 200, 32
out = {}
for variant in ("kernel-nominal", "kernel-pinned", "kernel-physics-only"):
    spec = resolve("CartPoleStayUp-v0", "default", {**rc.overrides_for("CartPoleStayUp-v0", variant), "n_envs": n,
                                                    "nepisodes": eps, "eval_episodes": 0})
    r = train(spec.env, spec.config, spec.agent_params)
    ends = np.cumsum(r.lengths, axis=1)  # [n, eps] step at which each episode ends
    T = int(ends.max())
    done = np.zeros((n, T + 1), np.int32)
    np.add.at(done, (np.repeat(np.arange(n), eps), ends.ravel()), 1)
    per_prog = done.reshape(n // block, block, T + 1).sum(1)  # [programs, steps]
    active = per_prog > 0
    out[variant] = dict(mean_len=float(r.lengths.mean()), steps_with_reset=float(active.mean()),
                        steps_over_group_capacity=float((per_prog > block // 4).mean()),
                        lanes_done_per_reset_step=float(per_prog[active].mean()))
    print(variant, out[variant], flush=True)
