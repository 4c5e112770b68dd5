"""The openai_ros exercise 2.5, the pole released at 30 degrees: can the cart-pole catch it, and does Q-learning?

Two measurements on the closed-form cart-pole (the same dynamics as MJX's, tested), pole at 0.5236 rad:

* feasibility: a bang-bang feedback policy (the big action toward ``sign(angle + k * angular velocity)``, both
  signs, k in 0 .. 1) flies 20 episodes for each controller and command step ``pos_step``; the best mean length
  says whether the task's own action set can hold the pole at all from there;
* learning: ``jaxrobo train``'s trainer (Q-learning, the default preset plus the listed overrides) on the same
  reset; the figure is the best table's mean greedy length on fresh episodes (the task's target is 500).

    python benchmarks/studies/exercise_2_5.py --out benchmarks/results/cpu-2cores/exercise_2_5.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import _common  # noqa: E402,F401  (the project root on sys.path)

ANGLE = 0.5236
WIDE = {"state_low": [-2.4, -3.0, -0.7, -4.0], "state_high": [2.4, 3.0, 0.7, 4.0], "bins": [1, 6, 14, 12]}
LEARNING = {
    "default preset": {},
    "wide angle bins": WIDE,
    "wide, position control": {**WIDE, "control_type": "position"},
    "wide, pos_step 0.1": {**WIDE, "pos_step": 0.1, "nepisodes": 2000},
    "wide, pos_step 0.5": {**WIDE, "pos_step": 0.5, "nepisodes": 2000},
    "pos_step 0.5, velocity to 20 m/s, shared table of 256 envs": {
        "pos_step": 0.5, "n_envs": 256, "nepisodes": 500, "shared_table": True, "alpha": 0.1,
        "state_low": [-2.4, -20, -0.7, -6], "state_high": [2.4, 20, 0.7, 6], "bins": [1, 10, 14, 12]},
}


def feasibility() -> list[dict]:
    import jax
    import jax.numpy as jnp

    import jaxrobo
    from jaxrobo.task.rollout import rollout

    rows = []
    for control in ("velocity", "position", "effort"):
        for pos_step in (0.016, 0.1, 0.5):
            env = jaxrobo.make("CartPoleStayUp-v0", backend="analytic", control_type=control,
                               init_pole_angle=ANGLE, pos_step=pos_step)
            best = 0.0
            for k in (0.0, 0.1, 0.3, 1.0):
                for toward in (True, False):
                    def policy(_key, obs, k=k, toward=toward):
                        lean = obs[2] + k * obs[3] > 0
                        return jnp.where(lean == toward, 3, 2)  # 3: right big, 2: left big
                    out = jax.jit(lambda key: rollout(env, policy, key, 20))(jax.random.key(0))
                    best = max(best, float(out["length"].mean()))
            rows.append({"control_type": control, "pos_step": pos_step, "best_feedback_mean_length": best})
            print(rows[-1], flush=True)
    return rows


def learning() -> list[dict]:
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    rows = []
    base = {"env.backend": "analytic", "init_pole_angle": ANGLE, "n_envs": 64, "eval_envs": 4}
    for name, sets in LEARNING.items():
        spec = resolve("CartPoleStayUp-v0", overrides={**base, **sets})
        t0 = time.perf_counter()
        s = train(spec.env, spec.config, spec.agent_params).summary()
        figure = s.get("selected_table_fresh_mean_length", s.get("eval_best_table_mean_length"))
        rows.append({"config": name, "overrides": sets, "env_steps": s["env_steps"], "greedy_mean_length": figure,
                     "target_met": bool(figure is not None and figure >= 500),
                     "seconds": round(time.perf_counter() - t0, 1)})
        print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="JSON path (default: print only)")
    args = p.parse_args(argv)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    data = {"device": jax.devices()[0].device_kind, "command": "python benchmarks/studies/exercise_2_5.py",
            "init_pole_angle": ANGLE, "feasibility": feasibility(), "learning": learning()}
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(data, f, indent=1)
        print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
