"""Where a Goto training step's XLA work goes: one knob at a time from the plan ``jaxrobo train`` builds.

    python benchmarks/studies/goto_ablation.py --device gpu --n-envs 262144,1048576 --steps 1000 --out rows.json \
        --hlo-dir hlo/

Each row trains ``--env`` (QuadcopterGoto-v2 by default; rigid, Q-learning, the preset's shared table and ``edges``
discretiser, records off: the chunk ``jaxrobo train`` compiles, :func:`jaxrobo.training.driver.compiled_chunk`) under
``ExecutionPlan.for_run``'s plan with one change (``--variants``, comma list):

``base``                   the plan as built (on a GPU: ``fused=pallas`` with the task's whole step as one
                           kernel, done envs gathered, an eighth of the batch at most)
``physics``                ``task_kernel`` off: only the robot's control step in a kernel, the rest of the
                           task's step (observation, outcome, reward, guard) XLA's
``rc:N`` / ``rc:/K``       ``reset_capacity`` N, or the batch over K (done envs gathered, reset, scattered back);
                           ``rc:all`` the plain select (every env reset, the done ones kept)
``group:G[:U]``            ``env_group`` G envs stepped at once (``unrolled_groups`` U, default 4)
``records``                ``record_episodes`` on (a table of ``--record-episodes`` slots per env)
``bins``                   the ``bins`` discretiser (3 per dimension: 6,561 states against the edges' 3,888)
                           instead of the preset's ``edges``
``per_env``                a table per env instead of the shared one (``+rows``: and ``carry_rows`` on)
``env``                    no learner: random actions, the env step and the autoreset only (``+disc``: the
                           discretiser's state index too), the reset as the base plan does it
``sarsa``                  the on-policy learner (a second epsilon-greedy selection per step)

Modifiers joined with ``+`` combine (``per_env+rows``, ``env+disc``, ``rc:/32+records``). Columns: env
steps/s, physics steps/s, ns per env step, kernels in the compiled chunk (fusions and library calls), compile
seconds, and the tables' checksum after one chunk (equal across plan-only variants: the same values; the learner
and table variants compute other things). ``--hlo-dir`` writes each row's optimised HLO (the compiled chunk's
``as_text()``) for counting the loop body's fusions and their shapes.
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

ENV = "QuadcopterGoto-v2"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None)
    p.add_argument("--env", default=ENV, choices=("QuadcopterGoto-v1", "QuadcopterGoto-v2"))
    p.add_argument("--n-envs", default="262144")
    p.add_argument("--variants", default="base,rc:/8,rc:/32,rc:1024,records,bins,env,env+disc")
    p.add_argument("--steps", type=int, default=1000, help="steps per compiled chunk")
    p.add_argument("--repeats", type=int, default=2, help="timed chunk calls per row (the fastest counts)")
    p.add_argument("--record-episodes", type=int, default=200, help="slots per env for the 'records' variant")
    p.add_argument("--hlo-dir", default=None)
    p.add_argument("--out", default=None)
    return p.parse_args(argv)


def kernels(text: str) -> int:
    return len(re.findall(r"\b(?:fusion|custom-call)\(", text))


def _env_only(trainer: Any, with_disc: bool) -> tuple[Any, Any]:
    """A chunk of env steps from random actions with the trainer's autoreset and nothing of the learner: the
    carry is ``(env_state, key, s_sum)``; ``s_sum`` accumulates the discretised state (``with_disc``) so that
    XLA keeps it."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.task import autoreset
    from jaxrobo.core import rng
    from jaxrobo.speed.plan import step_batch

    env, c, plan = trainer.env, trainer.config, trainer.plan

    def step(carry, params):
        state, key, s_sum = carry
        k_next, k_act, k_reset = (jax.vmap(rng.subkey, in_axes=(0, None, None))(key, i, 3) for i in range(3))
        a = jnp.minimum(jax.vmap(lambda k: rng.uniform(k, (), 0.0, float(env.num_actions)))(k_act)
                        .astype(jnp.int32), env.num_actions - 1)
        stepped = step_batch(env, state, a, params, plan)
        done = stepped.terminated | stepped.truncated | (stepped.steps >= c.nsteps)
        if with_disc:
            fresh = lambda k, _e: (jax.vmap(env.reset, in_axes=(0, None))(k, params),)  # noqa: E731
            state, = autoreset.reset_where(fresh, done, k_reset, (stepped,), trainer.reset_capacity)
            s_sum = s_sum + jax.vmap(trainer.disc)(state.obs)
        else:
            state = autoreset.autoreset(env, done, k_reset, params, stepped, trainer.reset_capacity)
        return state, k_next, s_sum

    def chunk(carry, params):
        return jax.lax.scan(lambda r, _: (step(r, params), None), carry, None, length=c.chunk_steps)[0]

    return chunk, step


def measure(n: int, variant: str, args: argparse.Namespace) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from jaxrobo.training import driver
    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    mods = variant.split("+")
    overrides: dict[str, Any] = {"n_envs": n, "chunk_steps": args.steps, **_common.TIMED_TRAINING,
                                 "backend": "rigid"}
    plan_changes: dict[str, Any] = {}
    agent = "qlearn"
    for m in mods:
        if m.startswith("rc:"):
            v = m[3:]
            plan_changes["reset_capacity"] = (None if v == "all" else -(-n // int(v[1:])) if v.startswith("/")
                                              else int(v))
        elif m.startswith("group:"):
            g, _, u = m[6:].partition(":")
            plan_changes["env_group"] = int(g)
            if u:
                plan_changes["unrolled_groups"] = int(u)
        elif m == "records":
            overrides.update(record_episodes=True, nepisodes=args.record_episodes)
        elif m == "bins":
            overrides.update(discretiser="bins", edges=None, number_splits=3)
        elif m == "per_env":
            overrides["shared_table"] = False
        elif m == "rows":
            plan_changes["carry_rows"] = True
        elif m == "sarsa":
            agent = "sarsa"
        elif m == "physics":
            plan_changes["task_kernel"] = False
        elif m in ("base", "env", "disc"):
            pass
        else:
            raise ValueError(f"variant {variant!r}: unknown part {m!r}")
    spec = resolve(args.env, "default", overrides, agent=agent)
    env, ap, ep = spec.env, spec.agent_params, spec.env.default_params
    plan = ExecutionPlan.for_run(env, spec.config).replace(**plan_changes)
    trainer = Trainer(env, spec.config, plan=plan)
    row: dict[str, Any] = {"env": args.env, "n_envs": n, "variant": variant, "execution_plan": repr(plan),
                           "steps": args.steps}
    t0 = time.perf_counter()
    if "env" in mods:
        chunk_fn, _ = _env_only(trainer, "disc" in mods)
        runner = jax.jit(trainer.init)(jax.random.key(0), ap, ep)
        carry = (runner.env_state, runner.key, jnp.zeros((n,), jnp.int32))
        del runner
        jitted = jax.jit(plan.traced(chunk_fn), donate_argnums=0)
        with plan.tracing():
            compiled = jitted.lower(carry, ep).compile()
        call = lambda c: compiled(c, ep)  # noqa: E731
        check = lambda c: jnp.sum(c[0].obs)  # noqa: E731
    else:
        runner = jax.jit(trainer.init)(jax.random.key(0), ap, ep)
        row["carry_bytes_per_env"] = _common.tree_bytes(runner) / n
        compiled = driver.compiled_chunk(trainer, runner, ap, ep)
        carry = runner
        call = lambda c: compiled(c, ap, ep)  # noqa: E731
        check = lambda c: _common.checksum(c.agent.q)  # noqa: E731
    row["compile_s"] = time.perf_counter() - t0
    text = compiled.as_text()
    row["kernels"] = kernels(text)
    if args.hlo_dir:
        os.makedirs(args.hlo_dir, exist_ok=True)
        with open(os.path.join(args.hlo_dir, f"{n}_{variant.replace(':', '_').replace('/', 'd')}.hlo.txt"), "w") as f:
            f.write(text)
    carry = call(carry)  # warm-up, and the values after one chunk
    row["checksum"] = float(jax.jit(check)(carry))
    best = float("inf")
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        carry = call(carry)
        jax.block_until_ready(carry)
        best = min(best, time.perf_counter() - t0)
    sps = n * args.steps / best
    row.update(seconds=best, steps_per_s=sps, physics_steps_per_s=sps * 30,
               ns_per_env_step=best / (n * args.steps) * 1e9)
    return row


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _common.select_device(args.device)
    import jax

    print(f"device {jax.devices()[0].device_kind} ({jax.default_backend()}), jax {jax.__version__}", flush=True)
    rows = []
    for n in [int(x) for x in args.n_envs.split(",")]:
        for variant in args.variants.split(","):
            try:
                row = measure(n, variant, args)
            except Exception as err:  # noqa: BLE001 - one failed row (memory) must not lose the others
                row = {"n_envs": n, "variant": variant, "error": f"{type(err).__name__}: {err}"[:400]}
            rows.append(row)
            if args.out:
                _common.write_json(rows, args.out)
            if "error" in row:
                print(f"n={n:<8d} {variant:18s} ERROR {row['error']}", flush=True)
                continue
            print(f"n={n:<8d} {variant:18s} {row['steps_per_s'] / 1e6:8.1f} M env/s "
                  f"{row['physics_steps_per_s'] / 1e9:6.2f}"
                  f" G phys/s {row['ns_per_env_step']:6.3f} ns/env-step  kernels {row['kernels']:4d}  compile "
                  f"{row['compile_s']:5.1f}s  check {row['checksum']:.7g}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
