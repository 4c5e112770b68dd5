"""The rigid quadcopter's control step alone (controller + physics, every substep; no task, no learner): the XLA
step (``off``: the substep loop rolled; ``xla``: written out) against the Pallas kernel of
:mod:`envs.quadcopter.kernel`, over batch sizes and the kernel's block size and warps.

    python benchmarks/studies/quadcopter_kernel.py --device gpu --n-envs 1024,65536,1048576 \
        --variants off,xla,pallas,pallas:128:4,pallas:512:8

    python benchmarks/studies/quadcopter_kernel.py --device gpu --n-envs 262144,1048576 --variants off,pallas \
        --env QuadcopterGoto-v2                      # the whole env step, random actions, no learner

``pallas`` runs the kernel through the robot's hook under ``fused="pallas"`` (as training does);
``pallas:BLOCK:WARPS`` calls it directly with that many envs and warps per program. Each timed call runs
``--steps`` control steps of the whole batch in one loop from random states (fixed random commands); columns:
control steps/s and physics steps/s (x ``n_substeps``). ``--env ID`` times that env's whole step instead (its
rigid backend, ``--running-step`` as its option, random actions, no learner; ``off`` and ``pallas`` only): what
the task's own XLA step adds to the physics. On a CPU the kernel runs interpreted, which measures nothing about
the GPU kernel.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common
import _common  # noqa: E402


def _compile_and_time(loop, carry, xs, repeats: int) -> tuple[float, float]:
    """``(compile seconds, seconds per call)`` of ``jax.jit(loop)`` on ``(carry, xs)`` (the fastest of ``repeats``)."""
    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(loop).lower(carry, xs).compile()
    compile_s = time.perf_counter() - t0
    seconds, _ = _common.time_carry(lambda c, x: compiled(c, x), carry, xs, repeats=repeats, min_seconds=0.25)
    return compile_s, seconds


def _write(rows: list[dict], out: str | None) -> None:
    if out:
        _common.write_json(rows, out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--n-envs", default="1024,65536")
    p.add_argument("--variants", default="off,xla,pallas", help="comma list: off, xla, pallas, pallas:BLOCK:WARPS")
    p.add_argument("--steps", type=int, default=20, help="control steps per timed call")
    p.add_argument("--running-step", type=float, default=0.3, help="control step (s): 0.3 = 30 substeps")
    p.add_argument("--env", default=None, help="time this env id's whole step instead of the control step")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    _common.select_device(args.device)
    import jax
    import jax.numpy as jnp

    from envs.quadcopter.robot import Quadcopter
    from envs.quadcopter.kernel import make_advance
    from jaxrobo.physics import fused
    from jaxrobo.physics.sim import JointState

    print(f"device {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}", flush=True)
    robot = Quadcopter("rigid", running_step=args.running_step)
    n_sub = robot.sim.n_substeps
    rows = []
    if args.env:
        return env_steps(args)
    for n in (int(x) for x in args.n_envs.split(",")):
        k = jax.random.split(jax.random.key(0), 3)
        yaw = jax.random.uniform(k[0], (n,), minval=-3.0, maxval=3.0)
        qpos = jnp.stack([jnp.zeros(n), jnp.zeros(n), jnp.ones(n), jnp.cos(yaw / 2), jnp.zeros(n), jnp.zeros(n),
                          jnp.sin(yaw / 2)], 1)
        state = JointState(qpos, 0.1 * jax.random.normal(k[1], (n, 6)))
        command = jax.random.uniform(k[2], (n, 4), minval=-1.0, maxval=1.0)
        for variant in args.variants.split(","):
            choice, *shape = variant.split(":")
            if shape:
                step = make_advance(robot, block=int(shape[0]), num_warps=int(shape[1]))
            else:
                step = jax.vmap(robot.advance)

            def loop(s, c, step=step, choice=choice):
                with fused.choose(choice):
                    s = jax.lax.fori_loop(0, args.steps, lambda _, x: step(x, c), s)
                return s, s.qpos[0, 0]

            compile_s, seconds = _compile_and_time(loop, state, command, args.repeats)
            sps = n * args.steps / seconds
            row = {"n_envs": n, "variant": variant, "n_substeps": n_sub, "control_steps_per_s": sps,
                   "physics_steps_per_s": sps * n_sub, "compile_s": compile_s}
            rows.append(row)
            print(f"n={n:<8d} {variant:16s} {sps / 1e6:10.1f} M control steps/s {sps * n_sub / 1e9:8.2f} G phys/s "
                  f"compile {compile_s:5.1f}s", flush=True)
    _write(rows, args.out)
    return 0


def env_steps(args: argparse.Namespace) -> int:
    import jax

    from jaxrobo.physics import fused
    from jaxrobo.training.run import resolve

    rows = []
    for n in (int(x) for x in args.n_envs.split(",")):
        spec = resolve(args.env, overrides=dict(n_envs=n, backend="rigid", running_step=args.running_step))
        env, params = spec.env, spec.env.default_params
        n_sub = env.robot.sim.n_substeps
        states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), n), params)
        actions = jax.random.randint(jax.random.key(1), (args.steps, n), 0, env.num_actions)
        for choice in args.variants.split(","):
            def loop(s, a, choice=choice):
                with fused.choose(choice):
                    step = jax.vmap(env.step, in_axes=(0, 0, None))
                    s = jax.lax.fori_loop(0, args.steps, lambda i, x: step(x, a[i], params), s)
                return s, s.reward.sum()

            compile_s, seconds = _compile_and_time(loop, states, actions, args.repeats)
            sps = n * args.steps / seconds
            rows.append({"env": args.env, "n_envs": n, "variant": choice, "n_substeps": n_sub, "env_steps_per_s": sps,
                         "physics_steps_per_s": sps * n_sub, "ns_per_env_step": 1e9 / sps, "compile_s": compile_s})
            print(f"{args.env} n={n:<8d} {choice:8s} {sps / 1e6:9.1f} M env steps/s {sps * n_sub / 1e9:7.2f} G phys/s "
                  f"{1e9 / sps:7.3f} ns/env step  compile {compile_s:4.1f}s", flush=True)
    _write(rows, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
