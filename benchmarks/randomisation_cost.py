"""Throughput cost of domain randomisation: training env steps/s of the kernels' tasks with ``randomise`` off and on.

The Pallas kernels take each env's drawn physics as per-env inputs, so a randomised run keeps the kernel the plan
gives a nominal one (the rigid Goto tasks, the analytic cart-pole with Q-learning, on one GPU from 1,024 envs).
This measures, per env id and batch size, each configuration trained ``--repeats`` times (2) in the same process,
in rounds of every configuration once (the fastest timing kept)::

    kernel-nominal       randomise off, the default plan (the kernel on a GPU)
    kernel-randomised    randomise on with ranges that change the physics (and observation noise), default plan
    xla-randomised       the same ranges on the XLA path (what the plan ran before the kernels took the draws:
                         fused="xla" for Goto, "off" for the cart-pole)
    kernel-physics-only  (only with --variants) randomise on, observation noise pinned at 0: the cart-pole's
                         kernel then skips the noise's hashes
    kernel-pinned        (only with --variants) randomise on, every range at its nominal value: the randomised
                         program on the nominal run's very episodes (its tables are the nominal kernel's bit for
                         bit), so the cost is the machinery's alone and not that of a harder task's shorter episodes

and prints the cost of randomisation in the kernel (1 - randomised / nominal, in %), each training's mean episode
length (randomised physics changes how long episodes last, and a chunk kernel's speed depends on how often envs
reset) and the kernel's gain over the XLA path under randomisation::

    python benchmarks/randomisation_cost.py --device gpu --n-envs 4096,65536,262144 --out rand_cost.json
    python benchmarks/randomisation_cost.py --device cpu --n-envs 64 --nepisodes 2     # smoke test

The ranges' widths do not change the cost (the same arithmetic runs at any width), except a noise level of exactly
0 in every env of a cart-pole program (kernel-physics-only).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _common  # noqa: E402

#: Per env id: the overrides of its fast backend, its randomisation ranges that change the physics, and the fused
#: choice of its XLA path under randomisation.
CASES = {
    "QuadcopterGoto-v2": ({"backend": "rigid", "shared_table": False, "snapshots": 0},
                          {"rand_mass": [0.9, 1.1], "rand_motor_gain": [0.9, 1.1], "rand_wind": [0.0, 0.5],
                           "rand_obs_noise": [0.0, 0.05]}, "xla"),
    "CartPoleStayUp-v0": ({"backend": "analytic"},
                          {"rand_cart_mass": [0.8, 1.2], "rand_pole_mass": [0.8, 1.2], "rand_pole_length": [0.9, 1.1],
                           "rand_obs_noise": [0.0, 0.01]}, "off"),
}
VARIANTS = ("kernel-nominal", "kernel-randomised", "xla-randomised", "kernel-physics-only", "kernel-pinned")


def overrides_for(env_id: str, variant: str) -> dict:
    """The config overrides of one variant (beside the batch size and budget)."""
    base, ranges, xla = CASES[env_id]
    if variant == "kernel-nominal":
        return dict(base)
    if variant == "kernel-randomised":
        return {**base, "randomise": True, **ranges}
    if variant == "xla-randomised":
        return {**base, "randomise": True, **ranges, "fused": xla}
    if variant == "kernel-physics-only":
        return {**base, "randomise": True, **ranges, "rand_obs_noise": [0.0, 0.0]}
    if variant == "kernel-pinned":  # the ranges' defaults are the nominal values
        return {**base, "randomise": True}
    raise ValueError(f"variant {variant!r}: one of {', '.join(VARIANTS)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default=None)
    ap.add_argument("--envs", default=",".join(CASES), help="comma list of env ids")
    ap.add_argument("--n-envs", default="4096,65536", help="comma list of batch sizes")
    ap.add_argument("--nepisodes", type=int, default=200,
                    help="episodes per env of each timed training (at 20 a cart-pole training on a GPU runs 0.1 s, "
                         "too short to time: two timings differ by up to 25 %%)")
    ap.add_argument("--variants", default=",".join(VARIANTS[:3]), help=f"comma list of {', '.join(VARIANTS)}")
    ap.add_argument("--repeats", type=int, default=2, help="timed trainings per variant (the fastest is kept)")
    ap.add_argument("--out", default=None, help="JSON of the rows")
    args = ap.parse_args()
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:  # before anything compiles or trains
        ap.error(f"--variants {','.join(unknown)}: expected a comma list of {', '.join(VARIANTS)}")
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: expected 1 or more")
    _common.select_device(args.device)
    from jaxrobo.speed.cache import enable_or_warn

    enable_or_warn("randomisation_cost")  # a variant's later trainings load its compiled program from the cache
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train
    from jaxrobo.training.trainer import Trainer

    def write(rows):
        if args.out:
            with open(args.out, "w") as f:
                json.dump(rows, f, indent=1)

    rows = []
    for env_id in args.envs.split(","):
        for n in (int(v) for v in args.n_envs.split(",")):
            specs, plans = {}, {}
            for variant in variants:
                specs[variant] = resolve(env_id, "default", {**overrides_for(env_id, variant), "n_envs": n,
                                                             "nepisodes": args.nepisodes, "eval_episodes": 0})
                plans[variant] = Trainer(specs[variant].env, specs[variant].config).plan
                if variant.startswith("kernel") and plans[variant].fused != "pallas":
                    print(f"note: {variant} runs without the kernel here ({plans[variant]!r}): the plan gives it on "
                          "one GPU from 1,024 envs", flush=True)
            # Repeats in rounds, each round every variant once in the given order: a drift of the card's clock
            # over the minutes of a call (power, heat) falls on every variant alike instead of on the later ones.
            runs = {variant: [] for variant in variants}
            for _ in range(args.repeats):
                for variant in variants:
                    spec = specs[variant]
                    result = train(spec.env, spec.config, spec.agent_params)
                    runs[variant].append((result.steps_per_second, result.compile_seconds, result.run_seconds,
                                          result.env_steps))
            rates = {}
            for variant in variants:
                best = max(r[0] for r in runs[variant])
                length = runs[variant][0][3] / (n * args.nepisodes)  # every env runs its nepisodes episodes
                rates[variant] = best
                rows.append({"env": env_id, "n_envs": n, "variant": variant, "steps_per_s": best,
                             "steps_per_s_each": [r[0] for r in runs[variant]], "mean_episode_length": length,
                             "compile_s": [r[1] for r in runs[variant]], "run_s": [r[2] for r in runs[variant]],
                             "plan": repr(plans[variant])})
                print(f"{env_id:20s} n={n:<8d} {variant:20s} {best / 1e6:9.3f} M steps/s   mean episode "
                      f"{length:7.1f} steps   {plans[variant]!r}", flush=True)
            write(rows)
            nominal = rates.get("kernel-nominal")
            for variant in ("kernel-randomised", "kernel-physics-only", "kernel-pinned"):
                if nominal and variant in rates:
                    cost = 100.0 * (1.0 - rates[variant] / nominal)
                    rows.append({"env": env_id, "n_envs": n, "variant": variant, "cost_percent": cost})
                    print(f"{env_id:20s} n={n:<8d} cost of randomisation in the kernel ({variant}): {cost:.1f} %",
                          flush=True)
            if "kernel-randomised" in rates and "xla-randomised" in rates:
                print(f"{env_id:20s} n={n:<8d} randomised: kernel / XLA path = "
                      f"{rates['kernel-randomised'] / rates['xla-randomised']:.2f}x", flush=True)
    write(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
