"""jaxrobo throughput, side by side with its peers, in one process on one device.

    python benchmarks/throughput.py                         # --quick: CPU-sized, a few minutes on 2 cores
    python benchmarks/throughput.py --device gpu --full     # every env, backend and learner, 1k..1M envs
    python benchmarks/throughput.py --device gpu --full --envs CartPoleStayUp-v0 --append   # the matrix in parts

For every registered jaxrobo env (cartpole on ``mjx``, on each Brax pipeline and on its closed-form ``analytic``
backend; the quadcopter tasks when registered) it measures env-steps per second over a list of ``n_envs``:

* ``env``: random actions, ``lax.scan`` rollout, auto-reset with fresh randomness;
* each learner: ``Trainer.run_chunk`` (act → step → discretise → learn → auto-reset) with ``record_episodes``
  off;

with the compile time (and whether it came from the persistent cache), memory per env (Q-table bytes, env
state bytes, the whole training carry per env; device memory where the backend reports it) and, for every
row, physics steps per second (env steps × substeps) and simulated seconds per wall second.

Peers, when the ``bench`` extra is installed: gymnax ``CartPole-v1`` (random-policy lax.scan), Brax
``inverted_pendulum`` on ``mjx``, Gymnasium ``CartPole-v1`` (numpy) single env, ``SyncVectorEnv`` and its
numpy-vectorised ``CartPoleVectorEnv``, and the seed-style loop (dict-based tabular Q-learning in plain Python
over Gymnasium ``CartPole-v1``). Anything missing is a ``skipped`` row with its reason.

Output: a table on stdout (each jaxrobo row's ratio to the best peer row and to the seed-style loop), and
``benchmarks/results/<device>/throughput.{json,csv,png}``.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import sys
import time
import traceback
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402

QUICK_N = (64, 1024, 16384)
FULL_N_CPU = (1, 16, 256, 4096)
FULL_N_GPU = (1024, 8192, 65536, 262144, 1048576)
ALL_LEARNERS = ("qlearn", "sarsa", "expected_sarsa", "double_q")
QUADCOPTERS = ("QuadcopterLiveShow-v0", "QuadcopterGoto-v1")
MIN_SAMPLE_SECONDS = 0.25  # a timed sample repeats a short call back to back until it lasts this long
MEMORY_FRACTION = 0.8  # skip sizes whose carry (+25 % for temporaries) needs more than this share of device memory


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None, help="JAX platform (default: JAX's choice)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CPU-sized default: few sizes, main rows only")
    size.add_argument("--full", action="store_true", help="every env × backend × learner at every size")
    p.add_argument("--n-envs", default=None, help="comma list of batch sizes (default by --quick/--full/device)")
    p.add_argument("--steps", type=int, default=None,
                   help="env steps per timed call (default: enough for ~0.1-1 s per call, 10..1000)")
    p.add_argument("--envs", default=None, help="comma list of env ids (default: every registered id)")
    p.add_argument("--backends", default=None,
                   help="comma list of cartpole backends (default: mjx, the three Brax pipelines and analytic)")
    p.add_argument("--learners", default=None,
                   help="comma list of learners, or 'none' (default quick: qlearn,sarsa; full: all four)")
    p.add_argument("--peers", default="gymnax,brax,gymnasium,gymnasium-sync,gymnasium-vec,seed-loop",
                   help="comma list of peers to run, or 'none'")
    p.add_argument("--fused", default=None, metavar="CHOICE[:BLOCK]",
                   help="jaxrobo rows under ExecutionPlan.fused=CHOICE (off, xla) and fused_block=BLOCK envs "
                        "(default: the plan's own choice)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per row (the minimum is kept)")
    p.add_argument("--out", default=None, help="output folder (default benchmarks/results/<device-name>)")
    p.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--append", action="store_true",
                   help="merge into the throughput.json already in the output folder (same device; a row measured "
                        "again replaces the old one), so a long matrix can run in parts")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats {args.repeats}: must be >= 1")
    if args.steps is not None and args.steps < 1:
        p.error(f"--steps {args.steps}: must be >= 1")
    if args.n_envs is not None:
        try:
            args.n_envs = tuple(int(x) for x in args.n_envs.split(",") if x.strip())
        except ValueError:
            p.error(f"--n-envs {args.n_envs!r}: expected a comma list of integers, e.g. 64,1024")
        if not args.n_envs or min(args.n_envs) < 1:
            p.error(f"--n-envs {args.n_envs!r}: sizes must be >= 1")
    return args


def steps_for(n: int, gpu: bool, requested: int | None) -> int:
    if requested is not None:
        return requested
    budget = 4_000_000 if gpu else 60_000  # env steps per timed call
    return int(min(1000, max(10, budget // n)))


# ---- jaxrobo rows ----------------------------------------------------------------------------------------------
def env_rollout(env: Any, n: int, steps: int, plan: Any):
    """``(state, key) -> (state, checksum)``: ``steps`` random-action steps of ``n`` auto-resetting envs, stepped
    as ``plan`` (a :class:`jaxrobo.plan.ExecutionPlan`) says."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.plan import step_batch
    from jaxrobo.wrappers import AutoReset

    wrapped = AutoReset(env)
    params = env.default_params
    n_actions = env.num_actions

    def rollout(carry, _):
        state, key = carry
        keys = jax.random.split(key, steps + 1)

        def body(c, k):
            s, acc = c
            a = jax.random.randint(k, (n,), 0, n_actions)
            s = step_batch(wrapped, s, a, params, plan)  # as the trainer steps them
            return (s, acc + s.reward), None

        (state, acc), _ = jax.lax.scan(body, (state, jnp.zeros(n, jnp.float32)), keys[1:])
        return (state, keys[0]), _common.checksum(state) + jnp.sum(acc)

    def init(key):
        return jax.vmap(wrapped.reset, in_axes=(0, None))(jax.random.split(key, n), params), key

    return init, rollout


def sim_info(env: Any) -> tuple[int, float]:
    from jaxrobo.env import simulator_of

    sim = simulator_of(env)
    n_sub = int(getattr(sim, "n_substeps", 1) or 1)
    running = float(getattr(sim, "running_step", 0.0) or 0.0)
    return n_sub, running


def fused_plan(env: Any, config: Any, fused: str | None) -> Any:
    """The run's plan, with ``--fused CHOICE[:BLOCK]`` applied when given."""
    from jaxrobo.plan import ExecutionPlan

    plan = ExecutionPlan.for_run(env, config)
    if fused is None:
        return plan
    choice, _, block = fused.partition(":")
    return plan.replace(fused=choice, fused_block=int(block) if block else None)


def measure_jaxrobo(env_id: str, backend: str | None, learner: str | None, n: int, args, ctx,
                    options: dict[str, Any] | None = None) -> dict[str, Any]:
    """One row: env-only (learner None) or training with ``learner``, at ``n`` envs; ``options`` are env options
    that differ from the defaults (shown beside the backend, e.g. ``mjx dt=0.02``)."""
    import jax

    from jaxrobo import driver
    from jaxrobo.run import resolve
    from jaxrobo.trainer import Trainer

    row = {"suite": "jaxrobo", "env": env_id, "backend": _backend_label(backend, options), "mode": learner or "env",
           "n_envs": n}
    overrides: dict[str, Any] = {"n_envs": n, **_common.TIMED_TRAINING, **(options or {})}
    if backend is not None:
        overrides["backend"] = backend
    steps = steps_for(n, ctx["gpu"], args.steps)
    overrides["chunk_steps"] = steps
    spec = resolve(env_id, "default", overrides, agent=learner)
    env = spec.env
    trainer = Trainer(env, spec.config, plan=fused_plan(env, spec.config, args.fused))
    plan = trainer.plan  # the run's execution plan, for env-only rows too (they step the envs as training does)
    row["execution_plan"] = repr(plan)
    state_shape = jax.eval_shape(env.reset, jax.random.key(0), env.default_params)
    row["env_state_bytes"] = _common.tree_bytes(state_shape)
    row["qtable_bytes"] = trainer.disc.n_states * env.num_actions * trainer.learner.n_tables * 4
    row["n_states"] = trainer.disc.n_states
    key = jax.random.key(0)
    if learner is None:
        init, rollout = env_rollout(env, n, steps, plan)
        carry_shape = jax.eval_shape(init, key)
    else:
        ap, ep = spec.agent_params, env.default_params
        carry_shape = jax.eval_shape(trainer.init, key, ap, ep)
    row["carry_bytes_per_env"] = _common.tree_bytes(carry_shape) / n
    limit = ctx["memory"].get("bytes_limit")
    need = _common.tree_bytes(carry_shape) * 1.25  # donated carry, updated in place, + temporaries
    if limit and need > MEMORY_FRACTION * limit:
        row.update(status="skipped", reason=f"needs ~{need / 2**30:.1f} GiB of {limit / 2**30:.1f} GiB device memory")
        return row

    if learner is None:
        carry = jax.jit(init)(key)
        jitted = jax.jit(plan.traced(rollout), donate_argnums=0, compiler_options=plan.xla_options)
        fn, compile_s, hit = _common.compile_timed(jitted, carry, 0, cache_dir=ctx["cache"])
        seconds, carry = _common.time_carry(lambda c, z: fn(c, z), carry, 0, repeats=args.repeats,
                                            min_seconds=MIN_SAMPLE_SECONDS)
    else:
        runner = jax.jit(trainer.init)(key, ap, ep)
        # The chunk exactly as ``jaxrobo train`` compiles and runs it (the host driver's).
        chunk, compile_s, hit = _common.timed(lambda: driver.compiled_chunk(trainer, runner, ap, ep), ctx["cache"])
        # The chunk returns the whole carry, so all of it is computed. The tables' checksum (a full read of
        # them: 126 MB at 16,384 cart-pole envs, ~40 % of a 10-step call on 2 cores) is taken once, untimed.
        seconds, runner = _common.time_carry(lambda r, _: (chunk(r, ap, ep), None), runner, 0,
                                             repeats=args.repeats, min_seconds=MIN_SAMPLE_SECONDS)
        row["q_checksum"] = float(jax.jit(_common.checksum)(runner.agent.q))
    n_sub, running = sim_info(env)
    sps = n * steps / seconds
    row.update(status="ok", steps=steps, seconds=seconds, steps_per_s=sps, compile_s=compile_s, compile_cached=hit,
               n_substeps=n_sub, control_dt=running, physics_dt=running / n_sub, physics_steps_per_s=sps * n_sub,
               sim_seconds_per_s=sps * running,
               **{f"device_{k}": v for k, v in _common.device_memory().items()})
    return row


# ---- peers -----------------------------------------------------------------------------------------------------
def peer_gymnax(n: int, args, ctx) -> dict[str, Any]:
    import gymnax
    import jax
    import jax.numpy as jnp

    env, params = gymnax.make("CartPole-v1")
    steps = steps_for(n, ctx["gpu"], args.steps)

    def init(key):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n), params)
        return state, key

    def rollout(carry, _):
        state, key = carry
        keys = jax.random.split(key, steps + 1)

        def body(c, k):
            s, acc = c
            ka, ks = jax.random.split(k)
            a = jax.random.randint(ka, (n,), 0, 2)
            out = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(ks, n), s, a, params)
            s, r = out[1], out[2]  # gymnax <1 returns 5 values, gymnax 1.x 6 (terminated, truncated)
            return (s, acc + r), None

        (state, acc), _ = jax.lax.scan(body, (state, jnp.zeros(n, jnp.float32)), keys[1:])
        return (state, keys[0]), _common.checksum(state) + jnp.sum(acc)

    return _time_jax_peer("gymnax", "CartPole-v1", n, steps, init, rollout, args, ctx, 1, 0.02)


def peer_brax(n: int, args, ctx) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from jaxrobo.sim import quiet_imports

    with quiet_imports():
        from brax import envs
        from brax.envs.wrappers import training

        base = envs.get_environment("inverted_pendulum", backend="mjx")
    env = training.wrap(base, episode_length=1000)
    steps = steps_for(n, ctx["gpu"], args.steps)

    def init(key):  # Brax wants raw uint32 keys
        return env.reset(jax.random.key_data(jax.random.split(key, n))), key

    def rollout(carry, _):
        state, key = carry
        keys = jax.random.split(key, steps + 1)

        def body(c, k):
            s, acc = c
            a = jax.random.uniform(k, (n, env.action_size), minval=-1.0, maxval=1.0)
            s = env.step(s, a)
            return (s, acc + s.reward), None

        (state, acc), _ = jax.lax.scan(body, (state, jnp.zeros(n, jnp.float32)), keys[1:])
        return (state, keys[0]), _common.checksum(state.pipeline_state) + jnp.sum(acc)

    return _time_jax_peer("brax", "inverted_pendulum/mjx", n, steps, init, rollout, args, ctx,
                          int(base._n_frames), float(base.dt))


def brax_physics_dt() -> float | str:
    """Brax ``inverted_pendulum``'s physics step on ``mjx`` (s), or why it cannot be read."""
    try:
        from jaxrobo.sim import quiet_imports

        with quiet_imports():
            from brax import envs
            base = envs.get_environment("inverted_pendulum", backend="mjx")
        return float(f"{float(base.sys.opt.timestep):.6g}")  # stored as float32 (0.019999999552965164)
    except Exception as err:  # brax missing or changed: the matched rows are skipped with this reason
        return f"{type(err).__name__}: {str(err)[:120]}"


def _backend_label(backend: str | None, options: dict[str, Any] | None) -> str:
    label = backend or "-"
    if options and "timestep" in options:
        label += f" dt={options['timestep']:g}"
    return label


def _time_jax_peer(suite, env_id, n, steps, init, rollout, args, ctx, n_sub, control_dt) -> dict[str, Any]:
    import jax

    carry = jax.jit(init)(jax.random.key(0))
    fn, compile_s, hit = _common.compile_timed(jax.jit(rollout, donate_argnums=0), carry, 0, cache_dir=ctx["cache"])
    seconds, _ = _common.time_carry(lambda c, z: fn(c, z), carry, 0, repeats=args.repeats,
                                    min_seconds=MIN_SAMPLE_SECONDS)
    sps = n * steps / seconds
    return {"suite": suite, "env": env_id, "backend": "-", "mode": "env", "n_envs": n, "status": "ok",
            "steps": steps, "seconds": seconds, "steps_per_s": sps, "compile_s": compile_s, "compile_cached": hit,
            "n_substeps": n_sub, "physics_steps_per_s": sps * n_sub, "sim_seconds_per_s": sps * control_dt}


def _numpy_row(suite, mode, n, steps, seconds, extra=None) -> dict[str, Any]:
    sps = steps / seconds
    row = {"suite": suite, "env": "CartPole-v1", "backend": "numpy", "mode": mode, "n_envs": n, "status": "ok",
           "steps": steps, "seconds": seconds, "steps_per_s": sps, "n_substeps": 1, "physics_steps_per_s": sps,
           "sim_seconds_per_s": sps * 0.02}
    row.update(extra or {})
    return row


def peer_gymnasium(n: int, args, ctx) -> dict[str, Any]:
    import numpy as np

    env = _common.make_gym_cartpole()
    total = 20_000 if not args.full else 100_000
    actions = np.random.default_rng(0).integers(0, 2, total)
    best = float("inf")
    for _ in range(args.repeats):
        env.reset(seed=0)
        t0 = time.perf_counter()
        for a in actions:
            _, _, term, trunc, _ = env.step(int(a))
            if term or trunc:
                env.reset()
        best = min(best, time.perf_counter() - t0)
    return _numpy_row("gymnasium", "env", 1, total, best)


def peer_gymnasium_vec(n: int, args, ctx, sync: bool) -> dict[str, Any]:
    import gymnasium as gym
    import numpy as np

    if sync:
        env = gym.vector.SyncVectorEnv([_common.make_gym_cartpole for _ in range(n)])
    else:
        env = gym.make_vec("CartPole-v1", num_envs=n, vectorization_mode="vector_entry_point")
    calls = max(20, min(2000, (20_000 if sync else 400_000) // n))
    actions = np.random.default_rng(0).integers(0, 2, (calls, n))
    best = float("inf")
    env.reset(seed=0)
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        best = min(best, time.perf_counter() - t0)
    env.close()
    return _numpy_row("gymnasium-sync" if sync else "gymnasium-vec", "env", n, calls * n, best)


def peer_seed_loop(n: int, args, ctx) -> dict[str, Any]:
    import random

    env = _common.make_gym_cartpole()
    agent = _common.DictQLearn(env.action_space.n, 0.1, 0.5, 0.9, random.Random(0))
    total = 20_000 if not args.full else 200_000
    best = float("inf")
    for _ in range(args.repeats):
        out = _common.seed_loop(env, agent, nepisodes=10**9, nsteps=1000, max_steps=total)
        best = min(best, out["seconds"] / out["steps"])
    return _numpy_row("seed-loop", "qlearn", 1, total, best * total,
                      {"qtable_bytes": None, "note": "dict Q-table in plain Python, one core"})


# ---- orchestration ---------------------------------------------------------------------------------------------
def _skip(suite, env, backend, mode, n, reason) -> dict[str, Any]:
    return {"suite": suite, "env": env, "backend": backend, "mode": mode, "n_envs": n, "status": "skipped",
            "reason": reason}


def _guard(fn, skip_row, *a) -> dict[str, Any]:
    try:
        return fn(*a)
    except ImportError as err:
        return {**skip_row, "reason": f"not installed ({err.name or err}); pip install 'jaxrobo[bench]'"}
    except Exception as err:  # noqa: BLE001 - a failing row is reported, not fatal
        traceback.print_exc(limit=3, file=sys.stderr)
        return {**skip_row, "status": "error", "reason": f"{type(err).__name__}: {str(err)[:200]}"}


def jaxrobo_plan(args, n_list, gpu: bool = False) -> list[tuple]:
    """("run", env_id, backend, learner, n, options) rows, plus ("skip", env_id, reason) for ids not there."""
    import jaxrobo
    from envs.cartpole import BACKENDS

    ids = jaxrobo.registered()
    wanted = args.envs.split(",") if args.envs else ids + [q for q in QUADCOPTERS if q not in ids]
    backends = tuple(args.backends.split(",")) if args.backends else BACKENDS
    for b in backends:
        if b not in BACKENDS:
            raise SystemExit(f"--backends {b!r}: allowed values are {', '.join(BACKENDS)}")
    if args.learners == "none":
        learners: tuple = ()
    elif args.learners:
        learners = tuple(args.learners.split(","))
        for name in learners:
            if name not in ALL_LEARNERS:
                raise SystemExit(f"--learners {name!r}: allowed values are {', '.join(ALL_LEARNERS)} or none")
    else:
        learners = ALL_LEARNERS if args.full else ("qlearn", "sarsa")
    plan = []
    last = n_list[-1:]
    for env_id in wanted:
        if env_id not in ids:
            plan.append(("skip", env_id, f"{env_id} is not registered in this checkout"))
            continue
        cartpole = env_id.startswith("CartPoleStayUp")
        env_backends = (backends if env_id == "CartPoleStayUp-v0" else ("mjx",)) if cartpole else (None,)
        for backend in env_backends:
            main = env_id == "CartPoleStayUp-v0" and backend in ("mjx", "analytic")
            if args.full:  # everything at every size
                env_sizes, learner_sizes = n_list, {name: n_list for name in learners}
            elif main:  # quick: the headline rows at every size, the other learners at the largest
                env_sizes = n_list
                learner_sizes = {name: (n_list if i == 0 else last) for i, name in enumerate(learners)}
            elif env_id == "CartPoleStayUpLeftRight-v0":  # same physics as v0: its 2-action learner at the largest size
                env_sizes, learner_sizes = (), {name: last for name in learners[:1]}
            elif cartpole:  # Brax pipelines: physics only, largest size
                env_sizes, learner_sizes = last, {}
            else:  # other tasks (quadcopters): physics and the first learner at the largest size
                env_sizes, learner_sizes = last, {name: last for name in learners[:1]}
            for n in env_sizes:
                plan.append(("run", env_id, backend, None, n, None))
            for name, sizes in learner_sizes.items():
                for n in sizes:
                    plan.append(("run", env_id, backend, name, n, None))
            if main and backend == "mjx" and "brax" in args.peers.split(","):
                plan.extend(_matched_rows(env_id, learners, _brax_sizes(args, n_list, gpu)))
    return plan


def _matched_rows(env_id: str, learners: tuple, sizes) -> list[tuple]:
    """Cart-pole on MJX at Brax ``inverted_pendulum``'s physics step, beside the Brax rows.

    Both control at 0.04 s a step, but the cart-pole's default physics step is 0.01 s (4 MJX steps per env step)
    and Brax's pendulum's 0.02 s (2): at the same physics step the two rows do the same physics work per env
    step, so their ratio compares the frameworks rather than the integrators' step sizes."""
    dt = brax_physics_dt()
    if isinstance(dt, str):
        return [("skip", env_id, f"mjx at Brax's physics step: {dt}")]
    rows = []
    for n in sizes:
        rows.append(("run", env_id, "mjx", None, n, {"timestep": dt}))
        rows.extend(("run", env_id, "mjx", name, n, {"timestep": dt}) for name in learners[:1])
    return rows


def _brax_sizes(args, n_list, gpu: bool):
    """The sizes the Brax peer runs at: every size with ``--full``, else the largest (two largest on a GPU)."""
    return n_list if args.full else n_list[-2:] if gpu else n_list[-1:]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _common.select_device(args.device)
    import jax

    from jaxrobo.cache import enable_compilation_cache

    cache = None if args.no_cache else enable_compilation_cache()
    gpu = jax.default_backend() == "gpu"
    if args.device == "gpu" and not gpu:
        raise SystemExit("--device gpu: JAX found no GPU (install jax[cuda12])")
    n_list = args.n_envs or (FULL_N_GPU if (gpu and not args.quick) else FULL_N_CPU if args.full else QUICK_N)
    ctx = {"gpu": gpu, "cache": cache, "memory": _common.device_memory()}
    dev = _common.device_name()
    out_dir = args.out or os.path.join(_common.ROOT, "benchmarks", "results", dev)
    print(f"device {jax.devices()[0].device_kind} ({jax.default_backend()}, {jax.device_count()} device(s)); "
          f"n_envs {list(n_list)}; compile cache {cache or 'off'}", flush=True)

    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    earlier = load_earlier(out_dir, jax.devices()[0].device_kind) if args.append else None

    def add(row: dict[str, Any]) -> None:
        rows.append(row)
        print("  " + _line(row), flush=True)

    for item in jaxrobo_plan(args, n_list, gpu):
        if item[0] == "skip":
            add(_skip("jaxrobo", item[1], "-", "-", 0, item[2]))
            continue
        _, env_id, backend, learner, n, options = item
        add(_guard(measure_jaxrobo, _skip("jaxrobo", env_id, _backend_label(backend, options), learner or "env", n, ""),
                   env_id, backend, learner, n, args, ctx, options))

    peers = [] if args.peers == "none" else args.peers.split(",")
    for peer in peers:
        if peer == "gymnax":
            for n in n_list:
                add(_guard(peer_gymnax, _skip("gymnax", "CartPole-v1", "-", "env", n, ""), n, args, ctx))
        elif peer == "brax":
            for n in _brax_sizes(args, n_list, gpu):
                add(_guard(peer_brax, _skip("brax", "inverted_pendulum/mjx", "-", "env", n, ""), n, args, ctx))
        elif peer == "gymnasium":
            add(_guard(peer_gymnasium, _skip("gymnasium", "CartPole-v1", "numpy", "env", 1, ""), 1, args, ctx))
        elif peer in ("gymnasium-sync", "gymnasium-vec"):
            sync = peer == "gymnasium-sync"
            cap = 256 if sync else 65536
            for n in sorted({min(n, cap) for n in n_list}):
                add(_guard(peer_gymnasium_vec, _skip(peer, "CartPole-v1", "numpy", "env", n, ""), n, args, ctx, sync))
        elif peer == "seed-loop":
            add(_guard(peer_seed_loop, _skip("seed-loop", "CartPole-v1", "numpy", "qlearn", 1, ""), 1, args, ctx))
        else:
            raise SystemExit(f"--peers {peer!r}: allowed values are gymnax, brax, gymnasium, gymnasium-sync, "
                             "gymnasium-vec, seed-loop, none")

    meta = {"device": jax.devices()[0].device_kind, "device_name": dev, "backend": jax.default_backend(),
            "device_count": jax.device_count(), "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__, "argv": sys.argv,
            "n_envs": list(n_list), "total_seconds": time.perf_counter() - t_start, "compile_cache": cache,
            "device_memory": ctx["memory"]}
    if earlier is not None:
        rows, meta["parts"] = merge_rows(earlier, rows, meta)
        print(f"\nmerged with {len(meta['parts']) - 1} earlier part(s) in {out_dir}/throughput.json: ratios across "
              "parts compare rows measured in different processes")
    _ratios(rows)
    print()
    print(table(rows))
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "throughput.json"), "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=2, default=str)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(os.path.join(out_dir, "throughput.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    if not args.no_plot:
        plot(rows, os.path.join(out_dir, "throughput.png"), meta["device"])
    print(f"\nwrote {out_dir}/throughput.{{json,csv{',png' if not args.no_plot else ''}}} "
          f"in {meta['total_seconds']:.0f} s")
    return 0


def _row_key(row: dict[str, Any]) -> tuple:
    return row["suite"], row["env"], row["backend"], row["mode"], row["n_envs"]


def load_earlier(out_dir: str, device: str) -> dict[str, Any]:
    """The results already in ``out_dir`` for ``--append`` (none yet: an empty start); refuses another device's."""
    path = os.path.join(out_dir, "throughput.json")
    if not os.path.exists(path):
        return {"meta": None, "rows": []}
    with open(path) as f:
        earlier = json.load(f)
    if earlier["meta"]["device"] != device:
        raise SystemExit(f"--append: {path} holds results of {earlier['meta']['device']!r}, this is {device!r}; "
                         "choose another --out")
    return earlier


def merge_rows(earlier: dict[str, Any], rows: list[dict[str, Any]], meta: dict[str, Any]) -> tuple[list, list]:
    """Earlier rows not measured again, then this run's rows (each tagged with its part); the parts' argv list."""
    old_meta = earlier["meta"]
    parts = [] if old_meta is None else old_meta.get("parts") or [{"argv": old_meta["argv"], "jax": old_meta["jax"]}]
    part = len(parts)
    parts = parts + [{"argv": meta["argv"], "jax": meta["jax"]}]
    fresh = {_row_key(r) for r in rows}
    kept = [r for r in earlier["rows"] if _row_key(r) not in fresh]
    for r in kept:
        r.setdefault("part", 0)
    merged = kept + [{**r, "part": part} for r in rows]
    return sorted(merged, key=lambda r: r["suite"] != "jaxrobo"), parts  # stable: jaxrobo rows, then the peers


def _ratios(rows: list[dict[str, Any]]) -> None:
    for r in rows:  # recomputed from the rows at hand (with --append, earlier ratios may be stale)
        for k in ("x_best_peer", "best_peer", "x_seed_loop", "x_brax"):
            r.pop(k, None)
    peers = [r for r in rows if r["suite"] != "jaxrobo" and r.get("status") == "ok"]
    best = max(peers, key=lambda r: r["steps_per_s"], default=None)
    seed = next((r for r in peers if r["suite"] == "seed-loop"), None)
    brax_at = {r["n_envs"]: r for r in peers if r["suite"] == "brax"}
    for r in rows:
        if r["suite"] != "jaxrobo" or r.get("status") != "ok":
            continue
        if best is not None:
            r["x_best_peer"] = r["steps_per_s"] / best["steps_per_s"]
            r["best_peer"] = f"{best['suite']} n={best['n_envs']}"
        if seed is not None:
            r["x_seed_loop"] = r["steps_per_s"] / seed["steps_per_s"]
        brax = brax_at.get(r["n_envs"])
        if brax is not None and r["env"].startswith("CartPole"):
            r["x_brax"] = r["steps_per_s"] / brax["steps_per_s"]


def _fmt_rate(x: float | None) -> str:
    if x is None:
        return "-"
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= div:
            return f"{x / div:.2f}{unit}"
    return f"{x:.0f}"


def _line(r: dict[str, Any]) -> str:
    head = f"{r['suite']:14s} {r['env']:22s} {r['backend']:14s} {r['mode']:14s} n={r['n_envs']:<8}"
    if r.get("status") != "ok":
        return f"{head} {r.get('status')}: {r.get('reason', '')}"
    comp = f"compile {r['compile_s']:.1f}s{' (cache)' if r.get('compile_cached') else ''}" if "compile_s" in r else ""
    plan = f" {r['execution_plan']}" if "execution_plan" in r else ""
    return f"{head} {_fmt_rate(r['steps_per_s'])} steps/s {comp}{plan}"


def table(rows: list[dict[str, Any]]) -> str:
    """The stdout table: one line per row, ratios for jaxrobo rows."""
    hdr = (f"{'suite':14s} {'env':22s} {'backend':14s} {'mode':14s} {'n_envs':>8s} {'steps/s':>9s} "
           f"{'phys/s':>9s} {'sim s/s':>9s} {'compile':>8s} {'B/env':>9s} {'x best peer':>11s} {'x brax':>7s} "
           f"{'x seed':>8s}")
    lines = [hdr, "-" * len(hdr)]
    for r in rows:
        if r.get("status") != "ok":
            lines.append(f"{r['suite']:14s} {r['env']:22s} {r['backend']:14s} {r['mode']:14s} {r['n_envs']:>8} "
                         f"{r.get('status')}: {r.get('reason', '')}")
            continue
        comp = f"{r['compile_s']:.1f}s{'*' if r.get('compile_cached') else ''}" if "compile_s" in r else "-"
        kib = (r.get("carry_bytes_per_env") or 0) / 1024
        bpe = (f"{kib:.0f}KiB" if kib >= 10 else f"{kib:.1f}KiB") if kib else "-"
        xb = f"{r['x_best_peer']:.2f}" if "x_best_peer" in r else "-"
        xs = (f"{r['x_seed_loop']:.0f}" if r["x_seed_loop"] >= 10 else f"{r['x_seed_loop']:.2f}") \
            if "x_seed_loop" in r else "-"
        xbrax = f"{r['x_brax']:.2f}" if "x_brax" in r else "-"
        lines.append(f"{r['suite']:14s} {r['env']:22s} {r['backend']:14s} {r['mode']:14s} {r['n_envs']:>8} "
                     f"{_fmt_rate(r['steps_per_s']):>9s} {_fmt_rate(r.get('physics_steps_per_s')):>9s} "
                     f"{_fmt_rate(r.get('sim_seconds_per_s')):>9s} {comp:>8s} {bpe:>9s} {xb:>11s} {xbrax:>7s} "
                     f"{xs:>8s}")
    lines.append("compile: * = served from the persistent cache; B/env = training carry (env state + Q-table + "
                 "records) per env; x = steps/s ratio (x brax: to Brax inverted_pendulum/mjx at the same n_envs); "
                 "dt = physics step (s) where it differs from the default")
    plans = list(dict.fromkeys(r["execution_plan"] for r in rows if r.get("execution_plan")))
    if plans:
        lines.append("jaxrobo rows ran under " + "; ".join(plans))
    parts = {r.get("part", 0) for r in rows}
    if len(parts) > 1:
        lines.append(f"rows from {len(parts)} runs merged with --append (the JSON's meta.parts has their commands)")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: str, device: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[str, list[tuple[int, float]]] = {}
    for r in rows:
        if r.get("status") != "ok":
            continue
        name = f"{r['suite']}: {r['env']}" + (f" [{r['backend']}]" if r["backend"] not in ("-", "numpy") else "")
        name += f" {r['mode']}"
        series.setdefault(name, []).append((r["n_envs"], r["steps_per_s"]))
    fig, ax = plt.subplots(figsize=(10, 6.5))
    colours = plt.cm.tab20.colors  # 20 distinct colours; markers cycle too, so no two series look alike
    markers = "osD^v<>ph*"
    for i, (name, pts) in enumerate(sorted(series.items())):
        pts.sort()
        line = "-" if name.startswith("jaxrobo") else "--"
        ax.plot([p[0] for p in pts], [p[1] for p in pts], line, marker=markers[i % len(markers)],
                color=colours[i % len(colours)], label=name, markersize=5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("n_envs (parallel environments)")
    ax.set_ylabel("env steps per second")
    ax.set_title(f"throughput on {device}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
