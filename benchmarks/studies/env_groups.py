"""Training throughput against how the MJX batch is stepped: ``env_group`` and MJX's ``com_pos`` as is or lean.

An MJX step is many small kernels whose intermediates go to device memory between them. This script trains the
MJX cart-pole with Q-learning at each batch size, stepping the whole batch at once (``all``) or in the listed
group sizes (:func:`jaxrobo.speed.plan.step_batch`; ``--unrolled`` groups written out, more in a loop), each with
MJX's ``com_pos`` lean (:mod:`jaxrobo.physics.mjx_lean`, the default) and/or as MJX has it (``stock``). Each row is one
:class:`jaxrobo.speed.plan.ExecutionPlan` (printed with the row). It prints env-steps per second (minimum time of
``--repeats`` chunks after a warm-up) and a fingerprint of the Q-tables after the first chunk, which must be the
same for every row of a batch size.

    python benchmarks/studies/env_groups.py --device gpu --n-envs 262144,1048576 --groups all,65536 --mjx lean,stock
    python benchmarks/studies/env_groups.py --device cpu --n-envs 4096 --groups all,1024 --steps 20
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common
import _common  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--env", default="CartPoleStayUp-v0")
    p.add_argument("--backend", default=None, help="physics backend (default: the env's)")
    p.add_argument("--n-envs", default="262144,1048576", help="comma list of batch sizes")
    p.add_argument("--groups", default="all,65536", help="comma list of group sizes; 'all' = the whole batch")
    p.add_argument("--mjx", default="lean", help="comma list of lean (jaxrobo.physics.mjx_lean) and/or stock")
    p.add_argument("--unrolled", type=int, default=None,
                   help="groups written out before a loop takes over (default: the plan's unrolled_groups)")
    p.add_argument("--steps", type=int, default=100, help="training steps per timed chunk")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<device>/env_groups.json)")
    args = p.parse_args(argv)
    variants = args.mjx.split(",")
    if set(variants) - {"lean", "stock"}:
        p.error(f"--mjx {args.mjx}: expected a comma list of lean and stock")
    if args.unrolled is not None and args.unrolled < 1:
        p.error(f"--unrolled {args.unrolled}: expected an integer >= 1")
    _common.select_device(args.device)

    import jax
    import numpy as np

    from jaxrobo.training import driver
    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    rows = []
    for n, token, variant in ((int(n), g, v) for n in args.n_envs.split(",") for g in args.groups.split(",")
                              for v in variants):
        group = n if token == "all" else int(token)
        overrides = {"n_envs": n, **_common.TIMED_TRAINING, "chunk_steps": args.steps, "env_group": group}
        if args.backend is not None:
            overrides["backend"] = args.backend
        spec = resolve(args.env, "default", overrides, agent="qlearn")
        plan = ExecutionPlan.for_run(spec.env, spec.config).replace(lean_mjx=variant == "lean")
        if args.unrolled is not None:
            plan = plan.replace(unrolled_groups=args.unrolled)
        trainer = Trainer(spec.env, spec.config, plan=plan)
        ap, ep = spec.agent_params, spec.env.default_params
        runner = jax.jit(plan.traced(trainer.init))(jax.random.key(0), ap, ep)
        t0 = time.perf_counter()
        chunk = driver.compiled_chunk(trainer, runner, ap, ep)  # as ``jaxrobo train`` compiles it
        compile_s = time.perf_counter() - t0
        runner = chunk(runner, ap, ep)
        fingerprint = hashlib.sha256(np.asarray(runner.agent.q).tobytes()).hexdigest()[:12]
        seconds, _ = _common.time_carry(lambda r: (chunk(r, ap, ep), None), runner, repeats=args.repeats)
        row = {"env": args.env, "n_envs": n, "env_group": token, "mjx": variant,
               "unrolled_groups": plan.unrolled_groups, "execution_plan": repr(plan),
               "steps_per_s": n * args.steps / seconds, "compile_s": compile_s,
               "q_fingerprint_after_one_chunk": fingerprint}
        rows.append(row)
        print(f"n_envs={n} env_group={token} mjx={variant}: {row['steps_per_s'] / 1e6:.2f} M env-steps/s, "
              f"compile {compile_s:.1f} s, Q-tables after one chunk {fingerprint}; {plan!r}", flush=True)
    path = _common.write_json({"device": jax.devices()[0].device_kind, "jax": jax.__version__, "argv": sys.argv,
                               "rows": rows}, args.out, "env_groups.json")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
