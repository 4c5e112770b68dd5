"""PPO training throughput (env steps per second, the learner included) on the continuous cart-pole, beside
Brax's own ``inverted_pendulum`` (``mjx`` backend) under the same PPO settings: one run each, one device.

    python benchmarks/studies/ppo_throughput.py --device gpu
    python benchmarks/studies/ppo_throughput.py --device cpu --num-envs 16 --num-timesteps 20000 \
        --batch-size 16   # smoke

Both runs call ``brax.training.agents.ppo.train`` with the same hyperparameters and networks; jaxrobo's runs on
``CartPoleContinuous-v0`` through :class:`jaxrobo.interop.brax_env.BraxEnv` and ``wrap_for_training``, Brax's on its
``inverted_pendulum`` with Brax's own training wrapper. The figure is Brax's ``training/sps`` of the epochs after
the first (the first compiles), averaged over those epochs, and the whole call's env steps over its wall time
(compile included). Evaluation is off in both (``run_evals=False``), so only training is timed. Written to
``benchmarks/results/<device>/ppo_throughput.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common
import _common  # noqa: E402


def run(env, wrap_env_fn, settings: dict) -> dict:
    """One ``ppo.train`` call: steady-state sps (epochs after the first), and the whole call's steps over wall."""
    import functools

    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    sps = []
    t0 = time.perf_counter()
    kw = dict(settings)
    factory = functools.partial(ppo_networks.make_ppo_networks,
                                policy_hidden_layer_sizes=tuple(kw.pop("policy_hidden_layer_sizes")),
                                value_hidden_layer_sizes=tuple(kw.pop("value_hidden_layer_sizes")))
    _, _, _ = ppo.train(environment=env, wrap_env_fn=wrap_env_fn, network_factory=factory, run_evals=False,
                        max_devices_per_host=1,
                        progress_fn=lambda step, m: sps.append((int(step), float(m.get("training/sps", 0.0)))),
                        **kw)
    wall = time.perf_counter() - t0
    steps = sps[-1][0] if sps else 0
    steady = [s for _, s in sps[1:] if s > 0]
    return {"env_steps": steps, "wall_seconds": round(wall, 3),
            "steps_per_second_overall": round(steps / wall, 1),
            "steps_per_second_steady": round(sum(steady) / len(steady), 1) if steady else None,
            "epochs": len(sps), "sps_per_epoch": [round(s, 1) for _, s in sps]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=("cpu", "gpu"), default=None)
    parser.add_argument("--num-envs", type=int, default=2048)
    parser.add_argument("--num-timesteps", type=int, default=20_000_000)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--num-minibatches", type=int, default=16)
    parser.add_argument("--unroll-length", type=int, default=10)
    parser.add_argument("--episode-length", type=int, default=1000)
    parser.add_argument("--num-evals", type=int, default=6, help="epochs + 1 (the first epoch compiles)")
    parser.add_argument("--skip-brax", action="store_true", help="only jaxrobo's run")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    _common.select_device(args.device)
    import brax.envs

    from jaxrobo.interop import brax_env  # its import gives Brax 0.14's trainers the JAX calls they need

    settings = dict(num_timesteps=args.num_timesteps, num_envs=args.num_envs, batch_size=args.batch_size,
                    num_minibatches=args.num_minibatches, unroll_length=args.unroll_length,
                    episode_length=args.episode_length, num_evals=args.num_evals, num_updates_per_batch=4,
                    learning_rate=3e-4, entropy_cost=1e-2, discounting=0.97, normalize_observations=True,
                    reward_scaling=1.0, seed=0, policy_hidden_layer_sizes=[32, 32, 32, 32],
                    value_hidden_layer_sizes=[256, 256, 256, 256, 256])
    rows = {}
    print("jaxrobo CartPoleContinuous-v0 (analytic) ...", flush=True)
    rows["jaxrobo_CartPoleContinuous-v0"] = run(brax_env.make("CartPoleContinuous-v0"), brax_env.wrap_for_training,
                                                settings)
    print(rows["jaxrobo_CartPoleContinuous-v0"], flush=True)
    if not args.skip_brax:
        print("brax inverted_pendulum (mjx) ...", flush=True)
        try:
            env = brax.envs.get_environment("inverted_pendulum", backend="mjx")
            rows["brax_inverted_pendulum_mjx"] = run(env, None, settings)
        except Exception as err:  # noqa: BLE001 - a peer that cannot run is reported, not fatal
            rows["brax_inverted_pendulum_mjx"] = {"skipped": f"{type(err).__name__}: {err}"}
        print(rows["brax_inverted_pendulum_mjx"], flush=True)
    out = {"benchmark": "ppo_throughput", "device": _common.device_name(), "platform": platform.platform(),
           "settings": settings, "runs": rows,
           "command": "python benchmarks/studies/ppo_throughput.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    a, b = rows.get("jaxrobo_CartPoleContinuous-v0", {}), rows.get("brax_inverted_pendulum_mjx", {})
    if a.get("steps_per_second_steady") and b.get("steps_per_second_steady"):
        out["ratio_steady"] = round(a["steps_per_second_steady"] / b["steps_per_second_steady"], 2)
    path = _common.write_json(out, args.out, "ppo_throughput.json")
    print(json.dumps({k: v for k, v in out.items() if k != "settings"}, indent=1))
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
