"""Throughput cost of domain randomisation: training env steps/s with ``randomise`` off and on, same run otherwise.

With ``randomise`` on, each env carries its drawn physics and the step reads them; the Pallas kernels bake the
nominal model in, so a run the plan would give a kernel (the rigid Goto tasks, the analytic cart-pole with
Q-learning, on a GPU from 1,024 envs) takes the XLA path instead. This measures what that costs, per env id and
batch size, each configuration trained twice in the same process (the better of the two timings kept)::

    python benchmarks/randomisation_cost.py --device gpu --n-envs 4096,65536,262144
    python benchmarks/randomisation_cost.py --device cpu --n-envs 64 --nepisodes 4     # smoke test

``--ranges`` (default: every range of the task at a width that changes the physics) decides what is drawn; the
cost does not depend on the widths (the same arithmetic runs at any width).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

#: Per env id: the overrides of its fast backend and randomisation ranges that change the physics.
CASES = {
    "QuadcopterGoto-v2": ({"shared_table": False},
                          {"rand_mass": [0.9, 1.1], "rand_motor_gain": [0.9, 1.1], "rand_wind": [0.0, 0.5],
                           "rand_obs_noise": [0.0, 0.05]}),
    "CartPoleStayUp-v0": ({"backend": "analytic"},
                          {"rand_cart_mass": [0.8, 1.2], "rand_pole_mass": [0.8, 1.2], "rand_pole_length": [0.9, 1.1],
                           "rand_obs_noise": [0.0, 0.01]}),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default=None)
    ap.add_argument("--envs", default=",".join(CASES), help="comma list of env ids")
    ap.add_argument("--n-envs", default="4096,65536", help="comma list of batch sizes")
    ap.add_argument("--nepisodes", type=int, default=20, help="episodes per env of each timed training")
    ap.add_argument("--out", default=None, help="JSON of the rows")
    args = ap.parse_args()
    if args.device:
        os.environ["JAX_PLATFORMS"] = args.device
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train
    from jaxrobo.training.trainer import Trainer

    rows = []
    for env_id in args.envs.split(","):
        base, ranges = CASES[env_id]
        for n in (int(v) for v in args.n_envs.split(",")):
            rates = {}
            for label, extra in (("off", {}), ("on", {"randomise": True, **ranges})):
                spec = resolve(env_id, "default", {**base, **extra, "n_envs": n, "nepisodes": args.nepisodes,
                                                   "eval_episodes": 0})
                plan = Trainer(spec.env, spec.config).plan
                best = max(train(spec.env, spec.config, spec.agent_params).steps_per_second for _ in range(2))
                rates[label] = best
                rows.append({"env": env_id, "n_envs": n, "randomise": label, "steps_per_s": best, "plan": repr(plan)})
                print(f"{env_id:20s} n={n:<8d} randomise={label:3s} {best / 1e6:9.3f} M steps/s   {plan!r}", flush=True)
            print(f"{env_id:20s} n={n:<8d} cost of randomisation: on/off = {rates['on'] / rates['off']:.3f}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
