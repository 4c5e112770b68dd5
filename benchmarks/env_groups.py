"""Training throughput against ``env_group``: the envs the trainer steps at once (``Trainer.env_group``).

An MJX step is many small kernels whose intermediates go to device memory between them; while a batch's
intermediates fit in the GPU's L2 cache that traffic stays on chip. This script trains the MJX cart-pole with
Q-learning at each batch size, once stepping the whole batch at once (``all``) and once per listed group size
(:func:`jaxrobo.env.step_batch`), and prints env-steps per second (minimum time of ``--repeats`` chunks after a
warm-up) and a fingerprint of the Q-tables after the first chunk, which must be the same for every group size.

    python benchmarks/env_groups.py --device gpu --n-envs 262144,1048576 --groups all,65536
    python benchmarks/env_groups.py --device cpu --n-envs 4096 --groups all,1024 --steps 20
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--env", default="CartPoleStayUp-v0")
    p.add_argument("--backend", default=None, help="physics backend (default: the env's)")
    p.add_argument("--n-envs", default="262144,1048576", help="comma list of batch sizes")
    p.add_argument("--groups", default="all,65536", help="comma list of group sizes; 'all' = the whole batch")
    p.add_argument("--steps", type=int, default=100, help="training steps per timed chunk")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/env_groups.json)")
    args = p.parse_args(argv)
    _common.select_device(args.device)

    import jax
    import numpy as np

    from jaxrobo.run import resolve
    from jaxrobo.train import Trainer

    rows = []
    for n in (int(x) for x in args.n_envs.split(",")):
        for token in args.groups.split(","):
            group = n if token == "all" else int(token)
            overrides = {"n_envs": n, **_common.TIMED_TRAINING, "chunk_steps": args.steps, "env_group": group}
            if args.backend is not None:
                overrides["backend"] = args.backend
            spec = resolve(args.env, "default", overrides, agent="qlearn")
            trainer = Trainer(spec.env, spec.config)
            ap, ep = spec.agent_params, spec.env.default_params
            runner = jax.jit(trainer.init)(jax.random.key(0), ap, ep)
            t0 = time.perf_counter()
            chunk = jax.jit(trainer.run_chunk).lower(runner, ap, ep).compile()
            compile_s = time.perf_counter() - t0
            runner = chunk(runner, ap, ep)
            fingerprint = hashlib.sha256(np.asarray(runner.agent.q).tobytes()).hexdigest()[:12]
            seconds, _ = _common.time_carry(lambda r: (chunk(r, ap, ep), None), runner, repeats=args.repeats)
            row = {"env": args.env, "n_envs": n, "env_group": token, "steps_per_s": n * args.steps / seconds,
                   "compile_s": compile_s, "q_fingerprint_after_one_chunk": fingerprint}
            rows.append(row)
            print(f"n_envs={n} env_group={token}: {row['steps_per_s'] / 1e6:.2f} M env-steps/s, compile "
                  f"{compile_s:.1f} s, Q-tables after one chunk {fingerprint}", flush=True)
    path = args.out or os.path.join(_common.ROOT, "benchmarks", "results", _common.device_name(), "env_groups.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"device": jax.devices()[0].device_kind, "jax": jax.__version__, "argv": sys.argv, "rows": rows},
                  f, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
