"""The fused path (``ExecutionPlan.fused``) against the plain one: training throughput, kernels per step and memory
per env, over batch sizes, in one process on one device.

    python benchmarks/studies/fused.py --device gpu --n-envs 1024,16384,262144,1048576 --plans off,xla,xla:65536
    python benchmarks/studies/fused.py --device cpu --n-envs 16384 --plans off,xla:2048 \
        --envs CartPoleStayUp-v0:analytic
    python benchmarks/studies/fused.py --device gpu --n-envs 65536,262144,1048576 --plans off,xla,pallas \
        --envs CartPoleStayUp-v0:analytic --gymnax

Each row trains (Q-learning, records off, the chunk ``jaxrobo train`` compiles:
:func:`jaxrobo.training.driver.compiled_chunk`) under one plan: ``off`` (the plain path), ``xla`` (substeps written
out), ``xla:BLOCK`` (and the chunk's steps run block of BLOCK envs after block) or ``pallas`` (the chunk as one Pallas
kernel: :mod:`envs.cartpole.kernel`, the analytic cart-pole only; on a CPU it runs interpreted, which measures nothing
about the GPU kernel); ``pallas:BLOCK[:always][:lanes][:libdevice]`` sets its envs per program and turns its plan
choices off (:func:`plan_of`). The default chunk (4 M env steps per call, at least 10 steps) is short enough that a fast
kernel's calls time the fixed cost per call (the host's dispatch); ``--steps 1000`` times the chunk ``jaxrobo train``
runs by default. Columns: env steps/s, physics steps/s, simulated s/s, the compiled program's kernels (fusions and
library calls in the whole chunk, the step's loop body being nearly all of it), the training carry per env, and the
tables' checksum after one chunk (equal across plans: the same values). ``--gymnax`` adds gymnax's CartPole random
rollout at the same sizes (benchmarks/throughput.py's peer row). ``--learning SEEDS`` trains each env's default preset
under each plan instead, and prints what it learned (the plans' values can differ in the last bits on a GPU, where XLA
rounds written-out substeps differently; learning must not).
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import time
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common
import _common  # noqa: E402


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--n-envs", default="1024,16384", help="comma list of batch sizes")
    p.add_argument("--plans", default="off,xla",
                   help="comma list of off, xla, xla:BLOCK, "
                        "pallas, pallas:BLOCK[:always][:lanes][:libdevice]")
    p.add_argument("--envs", default="CartPoleStayUp-v0:analytic,QuadcopterGoto-v1",
                   help="comma list of env ids, each with :backend where it has a choice")
    p.add_argument("--steps", type=int, default=None, help="steps per timed chunk (default: by size)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--gymnax", action="store_true", help="also gymnax CartPole-v1 random rollout per size")
    p.add_argument("--learning", type=int, default=0, metavar="SEEDS",
                   help="instead: train each env's default preset under each plan from seeds 0..SEEDS-1 and "
                        "report its learning results (greedy evaluation, last training returns)")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    return p.parse_args(argv)


def kernels(compiled: Any) -> int:
    """Fusions and library calls in a compiled program's HLO: on a GPU, each is one kernel launch (or more)."""
    text = compiled.as_text()
    return len(re.findall(r"\b(?:fusion|custom-call)\(", text))


def plan_of(base: Any, choice: str) -> Any:
    """The plan a choice names: ``off``, ``xla[:BLOCK]``, ``pallas[:BLOCK][:always][:lanes][:libdevice]`` (BLOCK envs
    per program; ``always``: the reset's random numbers in every env every step, ``skip_resets`` off; ``lanes``:
    each lane hashes its own env's reset, ``group_resets`` off; ``libdevice``: libdevice's sin/cos calls,
    ``fast_sincos`` off)."""
    fused, *parts = choice.split(":")
    block, off = None, {}
    tokens = {"always": "skip_resets", "lanes": "group_resets", "libdevice": "fast_sincos"}
    for part in parts:
        if part in tokens:
            off[tokens[part]] = False
        elif part:
            block = int(part)
    if off and fused != "pallas":
        raise ValueError(f"plan {choice!r}: 'always', 'lanes' and 'libdevice' apply to pallas only")
    return base.replace(fused=fused, fused_block=block, **off)


def measure(env_spec: str, n: int, choice: str, args) -> dict[str, Any]:
    import jax

    from jaxrobo.training import driver
    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.training.run import resolve
    from jaxrobo.task.env import simulator_of
    from jaxrobo.training.trainer import Trainer

    env_id, _, backend = env_spec.partition(":")
    gpu = jax.default_backend() == "gpu"
    steps = args.steps or int(min(1000, max(10, (4_000_000 if gpu else 60_000) // n)))
    overrides = {"n_envs": n, "chunk_steps": steps, **_common.TIMED_TRAINING}
    if backend:
        overrides["backend"] = backend
    spec = resolve(env_id, "default", overrides, agent="qlearn")
    env, ap, ep = spec.env, spec.agent_params, spec.env.default_params
    plan = plan_of(ExecutionPlan.for_run(env, spec.config), choice)
    trainer = Trainer(env, spec.config, plan=plan)
    runner = jax.jit(trainer.init)(jax.random.key(0), ap, ep)
    row = {"env": env_spec, "n_envs": n, "plan": choice, "execution_plan": repr(plan), "steps": steps,
           "carry_bytes_per_env": _common.tree_bytes(runner) / n}
    t0 = time.perf_counter()
    chunk = driver.compiled_chunk(trainer, runner, ap, ep)
    row["compile_s"] = time.perf_counter() - t0
    row["kernels"] = kernels(chunk)
    # The tables after one chunk from the same start: equal across plans (the timed calls below run as many
    # chunks as fill the sample, which differs).
    runner = chunk(runner, ap, ep)
    row["q_checksum"] = float(jax.jit(_common.checksum)(runner.agent.q))
    seconds, runner = _common.time_carry(lambda r, _: (chunk(r, ap, ep), None), runner, 0, repeats=args.repeats,
                                         min_seconds=0.25)
    # The host's side of one call (it returns once the chunk is queued): where it is as long as the call itself,
    # the run is bound by dispatch, not by the device, and a longer chunk (--steps) measures the device.
    dispatch = []
    for _ in range(5):
        t0 = time.perf_counter()
        runner = chunk(runner, ap, ep)
        dispatch.append(time.perf_counter() - t0)
    jax.block_until_ready(runner)
    row["dispatch_s"] = sorted(dispatch)[2]
    # Steps per finished episode over the whole run so far: how often an env resets (the Pallas kernel's reset
    # branch is taken in a step where any env of a program is done).
    episodes = float(jax.numpy.sum(runner.episode.astype(jax.numpy.float32)))
    row["mean_episode_steps"] = float(jax.numpy.sum(runner.env_steps.astype(jax.numpy.float32))) / max(1.0, episodes)
    sim = simulator_of(env)
    n_sub, running = int(getattr(sim, "n_substeps", 1) or 1), float(getattr(sim, "running_step", 0.0) or 0.0)
    sps = n * steps / seconds
    row.update(seconds=seconds, steps_per_s=sps, physics_steps_per_s=sps * n_sub, sim_seconds_per_s=sps * running,
               ns_per_step_per_batch=seconds / steps * 1e9)
    return row


def learning(env_spec: str, choice: str, seed: int) -> dict[str, Any]:
    """One training run of the env's default preset under a plan: what it learned, not how fast."""
    import numpy as np

    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    env_id, _, backend = env_spec.partition(":")
    spec = resolve(env_id, "default", {"seed": seed, **({"backend": backend} if backend else {})})
    plan = plan_of(ExecutionPlan.for_run(spec.env, spec.config), choice)
    t0 = time.perf_counter()
    r = train(spec.env, spec.config, spec.agent_params, plan=plan)
    returns = np.asarray(r.returns)
    return {"env": env_spec, "plan": choice, "seed": seed, "seconds": time.perf_counter() - t0,
            "eval_return": float(np.mean(r.eval_returns)), "eval_length": float(np.mean(r.eval_lengths)),
            "last_returns": float(returns[..., -max(1, returns.shape[-1] // 10):].mean())}


def _write(path: str | None, rows: list[dict[str, Any]]) -> None:
    if path:
        _common.write_json(rows, path, default=str)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _common.select_device(args.device)
    import jax

    print(f"device {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}", flush=True)
    rows = []
    if args.learning:
        for env_spec in args.envs.split(","):
            for seed in range(args.learning):
                for choice in args.plans.split(","):
                    row = learning(env_spec, choice, seed)
                    rows.append(row)
                    _write(args.out, rows)
                    print(f"{env_spec:28s} seed {seed} {choice:10s} greedy return {row['eval_return']:9.3f} "
                          f"length {row['eval_length']:7.2f}  last 10 % training returns {row['last_returns']:9.3f}"
                          f"  ({row['seconds']:.1f}s)", flush=True)
        return 0
    sizes = [int(x) for x in args.n_envs.split(",")]
    targs = argparse.Namespace(steps=args.steps, repeats=args.repeats, full=False)
    ctx = {"gpu": jax.default_backend() == "gpu", "cache": None}
    # Size by size, gymnax's row right after the size's own, the JSON rewritten after each row: a run stopped at
    # its time limit keeps whole sizes.
    for n in sizes:
        for env_spec in args.envs.split(","):
            for choice in args.plans.split(","):
                try:
                    row = measure(env_spec, n, choice, args)
                except Exception as err:  # noqa: BLE001 - one failed row (memory) must not lose the others
                    row = {"env": env_spec, "n_envs": n, "plan": choice, "error": f"{type(err).__name__}: {err}"[:300]}
                rows.append(row)
                _write(args.out, rows)
                if "error" in row:
                    print(f"{env_spec:28s} n={n:<8d} {choice:10s} ERROR {row['error']}", flush=True)
                    continue
                print(f"{env_spec:28s} n={n:<8d} {choice:10s} {row['steps_per_s'] / 1e6:10.2f} M steps/s "
                      f"{row['physics_steps_per_s'] / 1e9:8.3f} G phys/s "
                      f"{row['sim_seconds_per_s'] / 1e3:10.1f} k sim s/s "
                      f"kernels {row['kernels']:4d}  {row['ns_per_step_per_batch'] / 1e3:9.1f} us/step  "
                      f"carry {row['carry_bytes_per_env']:7.0f} B/env  compile {row['compile_s']:5.1f}s  "
                      f"q {row['q_checksum']:.6g}  episode {row['mean_episode_steps']:.1f} steps  "
                      f"call {row['seconds'] * 1e3:.3f} ms, dispatch {row['dispatch_s'] * 1e3:.3f} ms", flush=True)
        if args.gymnax:
            import throughput

            try:
                row = throughput.peer_gymnax(n, targs, ctx)
            except Exception as err:  # noqa: BLE001
                row = {"suite": "gymnax", "n_envs": n, "error": str(err)[:300]}
            rows.append(row)
            _write(args.out, rows)
            print(f"gymnax CartPole-v1 random     n={n:<8d} {row.get('steps_per_s', 0) / 1e6:10.2f} M steps/s "
                  f"{row.get('status', '')} {row.get('reason', row.get('error', ''))}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
