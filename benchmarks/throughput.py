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

Peers, when the ``bench`` extra is installed (``bench-quad`` for crazyflow): gymnax ``CartPole-v1``
(random-policy lax.scan), Brax ``inverted_pendulum`` on ``mjx``, MuJoCo Playground ``CartpoleBalance`` on MJX,
crazyflow's quadrotor sim (random attitude commands around hover), Gymnasium ``CartPole-v1`` (numpy) single env,
``SyncVectorEnv`` and its numpy-vectorised ``CartPoleVectorEnv``, and the seed-style loop (dict-based tabular
Q-learning in plain Python over Gymnasium ``CartPole-v1``). Anything missing is a ``skipped`` row with its reason;
figures published by peers that cannot run here (crazyflow on an RTX 4090, L2F) are ``published`` rows.

The user's own commands (``--commands``): ``jaxrobo train`` and ``jaxrobo sweep`` with the default presets, each in a
fresh process, timed end to end (compile, training, evaluation, writing), under the seed's episode budget and the
step budget: useful env steps per second of that wall, with the useful share of env slots, beside the kernel rows
of the same task and size.

Output: a table on stdout (each row's physics step and substeps; each jaxrobo row's ratio per env step, per
physics step and per simulated second to the fastest peer of its family at the same n_envs, to Brax and to the
seed-style loop), ``throughput.{json,csv}``, the same table as plain text (``throughput.txt``) and the
figures of ``figures.py`` (published figures hatched: "published, other machine") under
``benchmarks/results/local/<device>/`` (git-ignored; ``--out benchmarks/results/h100`` updates a committed table
on purpose). ``--replot JSON`` redraws the table and figures of a results file without measuring.
"""
from __future__ import annotations

import argparse
import dataclasses
import csv
import json
import os
import platform
import sys
import time
import traceback
from typing import Any, Callable

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402
import figures  # noqa: E402
import time_to_trained  # noqa: E402
from figures import family  # noqa: E402  (the families ratios and figures group rows by)

QUICK_N = (64, 1024, 16384)
FULL_N_CPU = (1, 16, 256, 4096)
FULL_N_GPU = (1024, 8192, 65536, 262144, 1048576)
ALL_LEARNERS = ("qlearn", "sarsa", "expected_sarsa", "double_q")
QUADCOPTERS = ("QuadcopterLiveShow-v0", "QuadcopterGoto-v1")
MIN_SAMPLE_SECONDS = 0.25  # a timed sample repeats a short call back to back until it lasts this long
#: where a plain run writes (git-ignored); the committed tables are written on purpose with --out
LOCAL_RESULTS = ("benchmarks", "results", "local")
MEMORY_FRACTION = 0.8  # skip sizes whose carry (+25 % for temporaries) needs more than this share of device memory


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "gpu"), default=None, help="JAX platform (default: JAX's choice)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="CPU-sized default: few sizes, main rows only")
    size.add_argument("--full", action="store_true", help="every env × backend × learner at every size")
    p.add_argument("--n-envs", default=None, help="comma list of batch sizes (default by --quick/--full/device)")
    p.add_argument("--steps", type=int, default=None,
                   help="env steps per timed call (default: 10..1000, enough that a call times the path, not its "
                        "fixed cost; 1,000 for closed forms on a GPU)")
    p.add_argument("--envs", default=None, help="comma list of env ids (default: every registered id)")
    p.add_argument("--backends", default=None,
                   help="comma list of cartpole backends (default: mjx, the three Brax pipelines and analytic)")
    p.add_argument("--learners", default=None,
                   help="comma list of learners, or 'none' (default quick: qlearn,sarsa; full: all four)")
    p.add_argument("--peers", default=",".join(PEER_NAMES),
                   help=f"comma list of peers to run, or 'none' (default: all of {', '.join(PEER_NAMES)})")
    p.add_argument("--fused", default=None, metavar="CHOICE[:BLOCK]",
                   help="jaxrobo training rows under ExecutionPlan.fused=CHOICE (off, xla, pallas) and "
                        "fused_block=BLOCK envs (default: the plan's own choice)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per row (the minimum is kept)")
    p.add_argument("--commands", default=None,
                   help="the user's own commands as rows, timed end to end in a fresh process (compile, training, "
                        "evaluation and writing included): comma list of train-episodes, train-steps, "
                        "sweep-episodes, sweep-steps, or 'none' (default: all four on a GPU, train-steps on a "
                        "CPU)")
    p.add_argument("--command-envs", default="CartPoleStayUp-v0,QuadcopterGoto-v2",
                   help="env ids the --commands rows run, default presets (ID:BACKEND runs another backend, e.g. "
                        "CartPoleStayUp-v0:analytic)")
    p.add_argument("--command-n-envs", default=None,
                   help="comma list of n_envs for the --commands rows (default: 65536,262144,1048576 on a GPU, "
                        "256 on a CPU)")
    p.add_argument("--steps-per-env", type=int, default=None,
                   help="the step budget of the --commands rows: --total-steps n_envs x this (default on a GPU "
                        "10,000, about the useful work of the episode-budget rows; on a CPU 1,000)")
    p.add_argument("--time-to-trained", default=None, metavar="IDS",
                   help="the time-to-trained table first: each comma-listed task's default `jaxrobo train --env ID` "
                        "in fresh processes, cold and warm compile cache (benchmarks/time_to_trained.py; default: the "
                        "tabular tasks on a CPU, every shipped task on a GPU; none: skip)")
    p.add_argument("--out", default=None,
                   help="output folder (default benchmarks/results/local/<device-name>, git-ignored; the committed "
                        "tables are updated on purpose, e.g. --out benchmarks/results/h100)")
    p.add_argument("--replot", metavar="JSON", default=None,
                   help="measure nothing: print the table and write the figures of this throughput.json (into "
                        "--out, default its folder)")
    p.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    p.add_argument("--no-plot", action="store_true")
    p.add_argument("--append", action="store_true",
                   help="merge into the throughput.json already in the output folder (same device; a row measured "
                        "again replaces the old one), so a long matrix can run in parts")
    args = p.parse_args(argv)
    args.peers = [] if args.peers == "none" else [x for x in args.peers.split(",") if x.strip()]
    for peer in args.peers:
        if peer not in PEER_NAMES:
            p.error(f"--peers {peer!r}: allowed values are {', '.join(PEER_NAMES)} or none")
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


def steps_for(n: int, gpu: bool, requested: int | None, cheap: bool = False) -> int:
    """Env steps per timed call: ``requested``, else enough work that the call times the path rather than the
    host's fixed cost of a call (about a millisecond on a GPU: dispatch, arguments, the sync), 10..1000.

    ``cheap``: a closed-form step (jaxrobo's ``analytic``/``rigid`` backends, gymnax, crazyflow), where a GPU runs
    tens of G env steps/s, so the MJX-sized budget of 4 M env steps per call would time mostly that fixed cost.
    These take the longest chunk, 1,000 steps (``jaxrobo train``'s default ``chunk_steps``), whatever the batch."""
    if requested is not None:
        return requested
    if gpu and cheap:
        return 1000
    budget = 4_000_000 if gpu else 60_000  # env steps per timed call
    return int(min(1000, max(10, budget // n)))


# ---- the user's commands, end to end --------------------------------------------------------------------------
COMMANDS = ("train-episodes", "train-steps", "sweep-episodes", "sweep-steps")
#: Episodes per env of the episode-budget rows (``jaxrobo train ... --nepisodes 200``).
COMMAND_EPISODES = 200
#: A sweep row's grid: 4 configurations × (n_envs / 4 / SWEEP_ENVS) seeds × SWEEP_ENVS envs = n_envs env slots.
SWEEP_GRID, SWEEP_ENVS = "alpha=0.1,0.2,0.3,0.5", 64


def command_argv(kind: str, env_id: str, n: int, steps_per_env: int, out: str) -> list[str]:
    """The ``jaxrobo train`` / ``jaxrobo sweep`` command of a --commands row: the env's default preset, ``n``
    env slots in all (a sweep's rows × envs), the episode or the step budget."""
    command, budget = kind.split("-")
    env_id, _, backend = env_id.partition(":")
    extra = ["--set", f"env.backend={backend}"] if backend else []
    limit = (["--total-steps", str(n * steps_per_env)] if command == "train" else
             ["--total-steps", str(SWEEP_ENVS * steps_per_env)]) if budget == "steps" else []
    if command == "train":
        argv = ["train", "--env", env_id, "--n-envs", str(n), "--no-progress", "--out", out]
        if budget == "episodes":
            argv += ["--nepisodes", str(COMMAND_EPISODES)]
        return argv + limit + extra
    envs = min(SWEEP_ENVS, n)
    seeds = max(1, n // (4 * envs))
    argv = ["sweep", "--env", env_id, "--grid", SWEEP_GRID, "--seeds", str(seeds), "--n-envs", str(envs),
            "--no-plots", "--no-progress", "--out", out]
    if budget == "episodes":
        argv += ["--nepisodes", str(COMMAND_EPISODES)]
    return argv + limit + extra


def measure_command(kind: str, env_id: str, n: int, args, ctx) -> dict[str, Any]:
    """One --commands row: the command in a fresh process, its wall time from start to exit, and its useful env
    steps per second of that wall (``steps_per_s``), with its summary's useful share and wall split."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "run")
        per_env = args.steps_per_env or (10_000 if ctx["gpu"] else 1_000)
        argv = command_argv(kind, env_id, n, per_env, out)
        env = dict(os.environ)
        if args.device:
            env["JAX_PLATFORMS"] = "cuda" if args.device == "gpu" else "cpu"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "jaxrobo.cli", *argv], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"jaxrobo {' '.join(argv[:1])} exited {proc.returncode}: {proc.stderr[-800:]}")
        with open(os.path.join(out, "summary.json")) as f:
            s = json.load(f)
    command = argv[0]
    import jaxrobo

    name, _, backend = env_id.partition(":")
    n_sub, running = sim_info(jaxrobo.make(name, **({"backend": backend} if backend else {})))
    row = {"suite": "jaxrobo-cli", "env": name, "backend": backend or "default", "mode": kind, "n_envs": n,
           "n_substeps": n_sub, "physics_dt": running / n_sub, "physics_steps_per_s": s["env_steps"] * n_sub / wall,
           "sim_seconds_per_s": s["env_steps"] * running / wall,
           "status": "ok", "command": "jaxrobo " + " ".join(a if a != out else "OUT" for a in argv),
           "wall_s": wall, "env_steps": s["env_steps"], "steps_per_s": s["env_steps"] / wall,
           "useful_share": s.get("useful_share"), "compile_s": s.get("compile_seconds"),
           "run_s": s.get("run_seconds")}
    if command == "train":
        row.update(eval_s=s.get("eval_seconds"), write_s=s.get("write_seconds"), execution_plan=s.get("execution_plan"))
    row["steps_per_s_run"] = s["env_steps"] / max(s.get("run_seconds") or 1e-9, 1e-9)
    return row


def _gpu_visible() -> bool:
    """Whether a GPU is there, without starting JAX (``nvidia-smi`` answers)."""
    import shutil
    import subprocess

    exe = shutil.which("nvidia-smi")
    return bool(exe) and subprocess.run([exe, "-L"], capture_output=True).returncode == 0


def command_plan(args, gpu: bool) -> list[tuple]:
    """``(kind, env_id, n)`` of every --commands row."""
    if args.commands == "none":
        return []
    kinds = tuple(args.commands.split(",")) if args.commands else (COMMANDS if gpu else ("train-steps",))
    for k in kinds:
        if k not in COMMANDS:
            raise SystemExit(f"--commands {k!r}: allowed values are {', '.join(COMMANDS)} or none")
    sizes = tuple(int(x) for x in args.command_n_envs.split(",")) if args.command_n_envs else (
        (65536, 262144, 1048576) if gpu else (256,))
    return [(k, e, n) for e in args.command_envs.split(",") for n in sizes for k in kinds]


# ---- jaxrobo rows ----------------------------------------------------------------------------------------------
def env_rollout(env: Any, n: int, steps: int, plan: Any):
    """``(state, key) -> (state, checksum)``: ``steps`` random-action steps of ``n`` auto-resetting envs, stepped
    as ``plan`` (a :class:`jaxrobo.speed.plan.ExecutionPlan`) says."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.speed.plan import step_batch
    from jaxrobo.task.wrappers import AutoReset

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
    from jaxrobo.task.env import simulator_of

    sim = simulator_of(env)
    n_sub = int(getattr(sim, "n_substeps", 1) or 1)
    running = float(getattr(sim, "running_step", 0.0) or 0.0)
    return n_sub, running


def fused_plan(env: Any, config: Any, fused: str | None) -> Any:
    """The run's plan, with ``--fused CHOICE[:BLOCK]`` applied when given."""
    from jaxrobo.speed.plan import ExecutionPlan

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

    from jaxrobo.training import driver
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    label = _backend_label(backend, options)
    if learner and args.fused:  # a training row of another plan is another row (env-only rows never fuse)
        label += f" fused={args.fused}"
    row = {"suite": "jaxrobo", "env": env_id, "backend": label, "mode": learner or "env", "n_envs": n}
    overrides: dict[str, Any] = {"n_envs": n, **_common.TIMED_TRAINING, **(options or {})}
    if backend is not None:
        overrides["backend"] = backend
    spec = resolve(env_id, "default", overrides, agent=learner)
    env = spec.env
    steps = steps_for(n, ctx["gpu"], args.steps, cheap=env.robot.sim.cheap_step)
    spec = dataclasses.replace(spec, config=spec.config.replace(chunk_steps=steps))
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
    steps = steps_for(n, ctx["gpu"], args.steps, cheap=True)

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


def _brax_style_rollout(env: Any, action_size: int, n: int, steps: int, physics: Callable[[Any], Any]):
    """(init, rollout) of a Brax-style training env (``reset(keys)``/``step(state, action)`` over a batch of
    ``n``, auto-reset by its wrapper; Brax's own and Playground's): ``steps`` uniform random actions in [-1, 1]
    of ``action_size`` per env, the checksum over ``physics(state)`` and the summed rewards."""
    import jax
    import jax.numpy as jnp

    def init(key):  # the wrappers want raw uint32 keys, one per env
        return env.reset(jax.random.key_data(jax.random.split(key, n))), key

    def rollout(carry, _):
        state, key = carry
        keys = jax.random.split(key, steps + 1)

        def body(c, k):
            s, acc = c
            a = jax.random.uniform(k, (n, action_size), minval=-1.0, maxval=1.0)
            s = env.step(s, a)
            return (s, acc + s.reward), None

        (state, acc), _ = jax.lax.scan(body, (state, jnp.zeros(n, jnp.float32)), keys[1:])
        return (state, keys[0]), _common.checksum(physics(state)) + jnp.sum(acc)

    return init, rollout


def peer_brax(n: int, args, ctx) -> dict[str, Any]:
    from jaxrobo.physics.sim import quiet_imports

    with quiet_imports():
        from brax import envs
        from brax.envs.wrappers import training

        base = envs.get_environment("inverted_pendulum", backend="mjx")
    env = training.wrap(base, episode_length=1000)
    steps = steps_for(n, ctx["gpu"], args.steps)
    init, rollout = _brax_style_rollout(env, env.action_size, n, steps, lambda s: s.pipeline_state)
    return _time_jax_peer("brax", "inverted_pendulum/mjx", n, steps, init, rollout, args, ctx,
                          int(base._n_frames), float(base.dt))


def peer_playground(n: int, args, ctx) -> dict[str, Any]:
    """MuJoCo Playground's ``CartpoleBalance`` (dm_control's cart-pole on MJX), random actions, auto-reset by
    Playground's own Brax training wrapper, on MJX's JAX implementation (Playground defaults to MJX-Warp, which
    needs ``warp-lang`` and a CUDA GPU; the JAX one runs everywhere and is what our rows use too)."""
    from jaxrobo.physics.sim import quiet_imports

    with quiet_imports():
        from mujoco_playground import registry, wrapper

        base = registry.load("CartpoleBalance", config_overrides={"impl": "jax"})
    env = wrapper.wrap_for_brax_training(base, episode_length=1000, action_repeat=1)
    steps = steps_for(n, ctx["gpu"], args.steps)
    init, rollout = _brax_style_rollout(env, base.action_size, n, steps, lambda s: s.data)
    n_sub = int(base.n_substeps)
    return _time_jax_peer("playground", "CartpoleBalance", n, steps, init, rollout, args, ctx, n_sub,
                          float(base.dt), backend="mjx-jax")


#: crazyflow's quadrotor as a gym-style task: attitude commands at 100 Hz on its 500 Hz first-principles sim
CRAZYFLOW_FREQ, CRAZYFLOW_CONTROL_FREQ = 500, 100


def peer_crazyflow(n: int, args, ctx) -> dict[str, Any]:
    """crazyflow's vectorised quadrotor sim (first-principles dynamics, one drone per world), driven like an
    env: every control step a random attitude command around hover ([roll, pitch, yaw] within +-0.1 rad,
    thrust within +-10 % of the hover thrust), 5 sim steps, and the worlds whose drone left the 1 m box around
    its start (or hit the floor) reset by crazyflow's own masked reset."""
    import jax
    import jax.numpy as jnp

    from jaxrobo.physics.sim import quiet_imports

    with quiet_imports():
        import crazyflow.sim.functional as cf_functional
        from crazyflow.control import Control
        from crazyflow.sim import Sim

        sim = Sim(n_worlds=n, n_drones=1, control=Control.attitude, freq=CRAZYFLOW_FREQ,
                  attitude_freq=CRAZYFLOW_CONTROL_FREQ, device="gpu" if ctx["gpu"] else "cpu")
    sim_step, sim_reset = sim.build_step_fn(), sim.build_reset_fn()
    n_sub = CRAZYFLOW_FREQ // CRAZYFLOW_CONTROL_FREQ
    steps = steps_for(n * n_sub, ctx["gpu"], args.steps, cheap=True)  # a sim step is the unit of work here

    def lift(d):  # start 1 m above the floor (crazyflow's default pose rests on it)
        return d.replace(states=d.states.replace(pos=d.states.pos.at[..., 2].set(1.0)))

    data0, default = lift(sim.data), lift(sim.default_data)
    hover = float(jnp.ravel(sim.data.params.mass)[0]) * 9.81
    start = data0.states.pos[:, 0]

    def init(key):
        return data0, key

    def rollout(carry, _):
        data, key = carry
        keys = jax.random.split(key, steps + 1)

        def body(c, k):
            d, acc = c
            u = jax.random.uniform(k, (n, 1, 4), minval=-1.0, maxval=1.0)
            cmd = jnp.concatenate([0.1 * u[..., :3], hover * (1.0 + 0.1 * u[..., 3:])], axis=-1)
            d = sim_step(cf_functional.attitude_control(d, cmd), n_steps=n_sub)
            pos = d.states.pos[:, 0]
            out = (pos[:, 2] < 0.05) | jnp.any(jnp.abs(pos - start) > 1.0, axis=-1)
            d = sim_reset(d, default, out)
            return (d, acc + out.astype(jnp.float32)), None

        (data, acc), _ = jax.lax.scan(body, (data, jnp.zeros(n, jnp.float32)), keys[1:])
        return (data, keys[0]), _common.checksum(data.states) + jnp.sum(acc)

    return _time_jax_peer("crazyflow", "quadrotor cf21B_500", n, steps, init, rollout, args, ctx, n_sub,
                          1.0 / CRAZYFLOW_CONTROL_FREQ, backend="first-principles")


#: Figures published by peers that cannot run here (other hardware, or no installable package): shown as rows
#: marked ``published``, never part of a measured ratio.
PUBLISHED = (
    {"suite": "crazyflow", "env": "quadrotor cf21B_500", "backend": "first-principles", "mode": "env",
     "n_envs": 262144, "physics_steps_per_s": 914e6, "physics_dt": 1 / 500, "n_substeps": 1,
     "hardware": "RTX 4090",
     "source": "crazyflow 0.4.0 README, Performance (first-principles dynamics, one drone, sim steps/s)"},
    {"suite": "l2f", "env": "quadrotor", "backend": "CUDA", "mode": "env", "n_envs": None,
     "physics_steps_per_s": 20e9, "physics_dt": None, "n_substeps": 1, "hardware": "laptop RTX 4090",
     "source": "RLtools L2F (Eschmann et al., Learning to Fly in Seconds): ~20 G quadrotor sim steps/s, "
               "hand-written CUDA"},
)


def published_rows(names) -> list[dict[str, Any]]:
    """The published figures of the peers in ``names`` (the physics-step rate is what their authors report; the
    env-step rate is derived only where the control step is known)."""
    rows = []
    for fig in PUBLISHED:
        if fig["suite"] not in names:
            continue
        row = {**fig, "status": "published"}
        row["steps_per_s"] = fig["physics_steps_per_s"] / fig["n_substeps"]
        dt = fig["physics_dt"]
        row["sim_seconds_per_s"] = fig["physics_steps_per_s"] * dt if dt else None
        row["reason"] = f"published, other machine ({fig['hardware']}): {fig['source']}"
        rows.append(row)
    return rows


def brax_physics_dt() -> float | str:
    """Brax ``inverted_pendulum``'s physics step on ``mjx`` (s), or why it cannot be read."""
    try:
        from jaxrobo.physics.sim import quiet_imports

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


def _time_jax_peer(suite, env_id, n, steps, init, rollout, args, ctx, n_sub, control_dt,
                   backend: str = "-") -> dict[str, Any]:
    import jax

    carry = jax.jit(init)(jax.random.key(0))
    fn, compile_s, hit = _common.compile_timed(jax.jit(rollout, donate_argnums=0), carry, 0, cache_dir=ctx["cache"])
    seconds, _ = _common.time_carry(lambda c, z: fn(c, z), carry, 0, repeats=args.repeats,
                                    min_seconds=MIN_SAMPLE_SECONDS)
    sps = n * steps / seconds
    return {"suite": suite, "env": env_id, "backend": backend, "mode": "env", "n_envs": n, "status": "ok",
            "steps": steps, "seconds": seconds, "steps_per_s": sps, "compile_s": compile_s, "compile_cached": hit,
            "n_substeps": n_sub, "control_dt": control_dt, "physics_dt": control_dt / n_sub,
            "physics_steps_per_s": sps * n_sub, "sim_seconds_per_s": sps * control_dt}


def _numpy_row(suite, mode, n, steps, seconds, extra=None) -> dict[str, Any]:
    sps = steps / seconds
    row = {"suite": suite, "env": "CartPole-v1", "backend": "numpy", "mode": mode, "n_envs": n, "status": "ok",
           "steps": steps, "seconds": seconds, "steps_per_s": sps, "n_substeps": 1, "control_dt": 0.02,
           "physics_dt": 0.02, "physics_steps_per_s": sps, "sim_seconds_per_s": sps * 0.02}
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


#: the pip extra that installs each peer (default ``bench``)
EXTRA_OF = {"crazyflow": "bench-quad"}


def _guard(fn, skip_row, *a) -> dict[str, Any]:
    try:
        return fn(*a)
    except ImportError as err:
        extra = EXTRA_OF.get(skip_row["suite"], "bench")
        return {**skip_row, "reason": f"not installed ({err.name or err}); pip install 'jaxrobo[{extra}]'"}
    except Exception as err:  # noqa: BLE001 - a failing row is reported, not fatal
        traceback.print_exc(limit=3, file=sys.stderr)
        return {**skip_row, "status": "error", "reason": f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"}


def continuous(env_id: str) -> bool:
    """Whether ``env_id``'s actions are a Box: its task declares float actions (nothing is built)."""
    import jax.numpy as jnp

    from jaxrobo.task.registry import _lookup

    return jnp.issubdtype(_lookup(env_id).env_class().action_dtype, jnp.floating)


def jaxrobo_plan(args, n_list, gpu: bool = False) -> list[tuple]:
    """("run", env_id, backend, learner, n, options) rows, plus ("skip", env_id, reason) for ids not there."""
    import jaxrobo
    from envs.cartpole.robot import BACKENDS

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
        # tabular rows need Discrete actions; PPO's throughput: benchmarks/studies/ppo_throughput.py
        if continuous(env_id):
            plan.append(("skip", env_id, f"{env_id} has continuous (Box) actions: no tabular rows; "
                                         "benchmarks/studies/ppo_throughput.py measures PPO on it"))
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
            if main and backend == "mjx" and "brax" in args.peers:
                plan.extend(_matched_rows(env_id, learners, _brax_sizes(args, n_list, gpu)))
    return plan


#: Every peer ``--peers`` accepts, in the order they run; ``l2f`` is a published figure only (no package).
PEER_NAMES = ("gymnax", "brax", "playground", "crazyflow", "l2f", "gymnasium", "gymnasium-sync", "gymnasium-vec",
              "seed-loop")


def peer_plan(peer: str, args, n_list, gpu: bool) -> list[tuple]:
    """``(fn, skip_row, n, extra_args)`` for each row of ``peer``; ``fn`` None: the row is ``skip_row`` itself
    (a published figure)."""
    if peer == "gymnax":
        return [(peer_gymnax, _skip("gymnax", "CartPole-v1", "-", "env", n, ""), n, ()) for n in n_list]
    if peer == "brax":
        return [(peer_brax, _skip("brax", "inverted_pendulum/mjx", "-", "env", n, ""), n, ())
                for n in _brax_sizes(args, n_list, gpu)]
    if peer == "playground":  # MJX like Brax: the same sizes
        return [(peer_playground, _skip("playground", "CartpoleBalance", "mjx-jax", "env", n, ""), n, ())
                for n in _brax_sizes(args, n_list, gpu)]
    if peer == "crazyflow":  # beside the quadcopter rows: every size on a GPU (or with --full), else the largest
        sizes = n_list if (gpu or args.full) else n_list[-1:]
        rows = [(peer_crazyflow, _skip("crazyflow", "quadrotor cf21B_500", "first-principles", "env", n, ""), n, ())
                for n in sizes]
        return rows + [(None, r, r["n_envs"], ()) for r in published_rows(("crazyflow",))]
    if peer == "l2f":
        return [(None, r, r["n_envs"], ()) for r in published_rows(("l2f",))]
    if peer == "gymnasium":
        return [(peer_gymnasium, _skip("gymnasium", "CartPole-v1", "numpy", "env", 1, ""), 1, ())]
    if peer in ("gymnasium-sync", "gymnasium-vec"):
        sync = peer == "gymnasium-sync"
        cap = 256 if sync else 65536
        return [(peer_gymnasium_vec, _skip(peer, "CartPole-v1", "numpy", "env", n, ""), n, (sync,))
                for n in sorted({min(n, cap) for n in n_list})]
    if peer == "seed-loop":
        return [(peer_seed_loop, _skip("seed-loop", "CartPole-v1", "numpy", "qlearn", 1, ""), 1, ())]
    raise ValueError(f"unknown peer {peer!r}")  # parse_args has checked the names


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


def time_to_trained_plan(args: argparse.Namespace, gpu: bool) -> list[tuple[str, str | None]]:
    """``(env_id, agent)`` of the time-to-trained rows: ``--time-to-trained`` (``none``: no rows), else the
    tabular tasks on a CPU (their PPO runs take minutes on 2 cores) and every shipped task on a GPU."""
    given = args.time_to_trained
    if given == "none":
        return []
    tasks = time_to_trained.TASKS if gpu else tuple(t for t in time_to_trained.TASKS if t[1] is None)
    if given:
        known = {t[0]: t for t in time_to_trained.TASKS}
        for name in given.split(","):
            if name not in known:
                raise SystemExit(f"--time-to-trained {name!r}: allowed ids are {', '.join(known)} or none")
        tasks = tuple(known[name] for name in given.split(","))
    return list(tasks)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.replot:
        return replot(args.replot, args.out)
    if "crazyflow" in args.peers:  # crazyflow uses scipy's array-API mode, which scipy reads once, at its import
        os.environ.setdefault("SCIPY_ARRAY_API", "1")
    gpu_seen = args.device == "gpu" or args.device is None and _gpu_visible()
    trained_tasks = time_to_trained_plan(args, gpu_seen)
    if command_plan(args, gpu_seen) or trained_tasks:
        # The commands run in child processes beside this one: this one must not hold 75 % of the GPU's memory
        # from its first row on (XLA's default preallocation), or theirs fail to allocate.
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    _common.select_device(args.device)
    import jax

    from jaxrobo.speed.cache import enable_compilation_cache

    cache = None if args.no_cache else enable_compilation_cache()
    gpu = jax.default_backend() == "gpu"
    if args.device == "gpu" and not gpu:
        raise SystemExit("--device gpu: JAX found no GPU (install jax[cuda12])")
    n_list = args.n_envs or (FULL_N_GPU if (gpu and not args.quick) else FULL_N_CPU if args.full else QUICK_N)
    ctx = {"gpu": gpu, "cache": cache, "memory": _common.device_memory()}
    dev = _common.device_name()
    out_dir = args.out or os.path.join(_common.ROOT, *LOCAL_RESULTS, dev)
    print(f"device {jax.devices()[0].device_kind} ({jax.default_backend()}, {jax.device_count()} device(s)); "
          f"n_envs {list(n_list)}; compile cache {cache or 'off'}", flush=True)

    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    trained: list[dict[str, Any]] = []
    if trained_tasks:
        # The headline: what a user waits for, start to exit, beside the kernel rows below.
        print("time to a trained robot: each task's default `jaxrobo train --env ID`, fresh processes", flush=True)
        trained = time_to_trained.collect(trained_tasks, report=lambda r: print("  " + json.dumps(
            {k: r.get(k) for k in ("env_id", "cache", "wall_seconds", "learning_figure", "learning_value")}),
            flush=True))
        print(time_to_trained.table(trained), flush=True)
    earlier = load_earlier(out_dir, jax.devices()[0].device_kind) if args.append else None

    partial = os.path.join(out_dir, "throughput.partial.json")

    def add(row: dict[str, Any]) -> None:
        rows.append(row)
        print("  " + _line(row), flush=True)
        # Every row measured so far, on disk at once: a run stopped by a time limit keeps them (--replot it).
        _common.write_json({"meta": {"device": jax.devices()[0].device_kind, "argv": sys.argv, "partial": True},
                            "rows": rows}, partial, default=str)

    for item in jaxrobo_plan(args, n_list, gpu):
        if item[0] == "skip":
            add(_skip("jaxrobo", item[1], "-", "-", 0, item[2]))
            continue
        _, env_id, backend, learner, n, options = item
        add(_guard(measure_jaxrobo, _skip("jaxrobo", env_id, _backend_label(backend, options), learner or "env", n, ""),
                   env_id, backend, learner, n, args, ctx, options))

    for peer in args.peers:
        for fn, skip, n, extra in peer_plan(peer, args, n_list, gpu):
            add(_guard(fn, skip, n, args, ctx, *extra) if fn is not None else skip)

    for kind, env_id, n in command_plan(args, gpu):
        add(_guard(measure_command,
                   _skip("jaxrobo-cli", env_id.partition(":")[0], env_id.partition(":")[2] or "default", kind, n, ""),
                   kind, env_id, n, args, ctx))

    meta = {"device": jax.devices()[0].device_kind, "device_name": dev, "backend": jax.default_backend(),
            "device_count": jax.device_count(), "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__, "argv": sys.argv,
            "n_envs": list(n_list), "total_seconds": time.perf_counter() - t_start, "compile_cache": cache,
            "device_memory": ctx["memory"]}
    if earlier is not None:
        rows, meta["parts"] = merge_rows(earlier, rows, meta)
        print(f"\nmerged with {len(meta['parts']) - 1} earlier part(s) in {out_dir}/throughput.json: ratios across "
              "parts compare rows that different processes measured")
    _ratios(rows)
    print()
    print(table(rows))
    _common.write_json({"meta": meta, "rows": rows, "time_to_trained": trained},
                       os.path.join(out_dir, "throughput.json"), default=str)
    write_table(rows, meta, os.path.join(out_dir, "throughput.txt"))
    if os.path.exists(partial):
        os.remove(partial)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(os.path.join(out_dir, "throughput.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    written = [] if args.no_plot else figures.write_figures({"meta": meta, "rows": rows}, out_dir)
    pngs = ",".join(os.path.basename(w)[:-4] for w in written)
    print(f"\nwrote {out_dir}/throughput.{{json,csv,txt}}{f' and {{{pngs}}}.png' if pngs else ''} "
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


#: The three like-for-like measures: (row key, ratio key, what one unit is)
MEASURES = (("steps_per_s", "x_env", "env step"), ("physics_steps_per_s", "x_phys", "physics step"),
            ("sim_seconds_per_s", "x_sim", "simulated second"))
RATIO_KEYS = ("x_env", "x_phys", "x_sim", "peer", "x_seed_loop", "x_brax")


def _ratios(rows: list[dict[str, Any]]) -> None:
    """Each jaxrobo row against the fastest measured peer of its family at the same ``n_envs``, once per measure
    (env steps, physics steps, simulated seconds per wall second; ``peer`` names the peer(s) used); against
    Brax ``inverted_pendulum`` at the same ``n_envs`` and against the seed-style loop (cart-pole rows).
    Published figures (other hardware) never enter a ratio."""
    for r in rows:  # recomputed from the rows at hand (with --append, earlier ratios may be stale)
        for k in RATIO_KEYS + ("x_best_peer", "best_peer"):
            r.pop(k, None)
    peers = [r for r in rows if not r["suite"].startswith("jaxrobo") and r.get("status") == "ok"]
    seed = next((r for r in peers if r["suite"] == "seed-loop"), None)
    brax_at = {r["n_envs"]: r for r in peers if r["suite"] == "brax"}
    for r in rows:
        if r["suite"] != "jaxrobo" or r.get("status") != "ok":
            continue
        fam = family(r)
        if fam is None:
            continue
        same = [p for p in peers if family(p) == fam and p["n_envs"] == r["n_envs"] and p["suite"] != "seed-loop"]
        names = []
        for key, ratio, _ in MEASURES:
            cands = [p for p in same if p.get(key) and r.get(key)]
            if not cands:
                continue
            best = max(cands, key=lambda p: p[key])
            r[ratio] = r[key] / best[key]
            names.append(best["suite"])
        if names:
            r["peer"] = "/".join(dict.fromkeys(names)) + f" n={r['n_envs']}"
        if fam == "cart-pole":
            if seed is not None:
                r["x_seed_loop"] = r["steps_per_s"] / seed["steps_per_s"]
            brax = brax_at.get(r["n_envs"])
            if brax is not None:
                r["x_brax"] = r["steps_per_s"] / brax["steps_per_s"]


def _fmt_rate(x: float | None) -> str:
    if x is None:
        return "-"
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= div:
            return f"{x / div:.2f}{unit}"
    return f"{x:.0f}"


def _line(r: dict[str, Any]) -> str:
    n = "-" if r.get("n_envs") is None else r["n_envs"]
    head = f"{r['suite']:14s} {r['env']:22s} {r['backend']:14s} {r['mode']:14s} n={n:<8}"
    if r.get("status") == "published":
        return f"{head} {_fmt_rate(r['physics_steps_per_s'])} physics steps/s {r['reason']}"
    if r.get("status") != "ok":
        return f"{head} {r.get('status')}: {r.get('reason', '')}"
    if r["suite"] == "jaxrobo-cli":
        return (f"{head} {_fmt_rate(r['steps_per_s'])} useful env steps/s over {r['wall_s']:.1f} s wall "
                f"(compile {r.get('compile_s') or 0:.1f} s, run {r.get('run_s') or 0:.1f} s; "
                f"{(r.get('useful_share') or 0):.1%} useful slots)")
    comp = f"compile {r['compile_s']:.1f}s{' (cache)' if r.get('compile_cached') else ''}" if "compile_s" in r else ""
    plan = f" {r['execution_plan']}" if "execution_plan" in r else ""
    return f"{head} {_fmt_rate(r['steps_per_s'])} steps/s {comp}{plan}"


def _fmt_x(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x:.0f}" if x >= 100 else f"{x:.1f}" if x >= 10 else f"{x:.2f}"


def _fmt_dt(dt: float | None) -> str:
    return f"{dt:g}" if dt else "-"


def table(rows: list[dict[str, Any]]) -> str:
    """The stdout table: one line per row (physics step and substeps named), like-for-like ratios for jaxrobo
    rows."""
    head = f"{'suite':14s} {'env':22s} {'backend':16s} {'mode':14s} {'n_envs':>8s}"
    hdr = (f"{head} {'dt':>6s} {'sub':>3s} {'steps/s':>9s} {'phys/s':>9s} {'sim s/s':>9s} {'compile':>8s} "
           f"{'B/env':>9s} {'x env':>6s} {'x phys':>6s} {'x sim':>6s} {'x brax':>6s} {'x seed':>7s}  peer")
    lines = [hdr, "-" * len(hdr)]
    for r in rows:
        n = "-" if r.get("n_envs") is None else r["n_envs"]
        lead = f"{r['suite']:14s} {r['env'][:22]:22s} {r['backend'][:16]:16s} {r['mode']:14s} {n:>8}"
        status = r.get("status")
        if status not in ("ok", "published"):
            lines.append(f"{lead} {status}: {r.get('reason', '')}")
            continue
        phys = f"{_fmt_dt(r.get('physics_dt')):>6s} {r.get('n_substeps', '-'):>3}"
        rates = (f"{_fmt_rate(r.get('steps_per_s')):>9s} {_fmt_rate(r.get('physics_steps_per_s')):>9s} "
                 f"{_fmt_rate(r.get('sim_seconds_per_s')):>9s}")
        if status == "published":
            lines.append(f"{lead} {phys} {rates} {r['reason']}")
            continue
        comp = f"{r['compile_s']:.1f}s{'*' if r.get('compile_cached') else ''}" if "compile_s" in r else "-"
        kib = (r.get("carry_bytes_per_env") or 0) / 1024
        bpe = (f"{kib:.0f}KiB" if kib >= 10 else f"{kib:.1f}KiB") if kib else "-"
        xs = " ".join(f"{_fmt_x(r.get(k)):>6s}" for k in ("x_env", "x_phys", "x_sim", "x_brax"))
        lines.append(f"{lead} {phys} {rates} {comp:>8s} {bpe:>9s} {xs} {_fmt_x(r.get('x_seed_loop')):>7s}  "
                     f"{r.get('peer', '')}")
    lines.append("dt = physics step (s), sub = physics steps per env step; steps/s, phys/s, sim s/s = env steps, "
                 "physics steps and simulated seconds per wall second")
    lines.append("x env, x phys, x sim = the row's rate per env step, per physics step and per simulated second "
                 "over the fastest measured peer of the same family (cart-pole, quadcopter) at the same n_envs, "
                 "per measure (peer names it); x brax = env steps/s over Brax inverted_pendulum/mjx at the same "
                 "n_envs; x seed = env steps/s over the seed-style loop (cart-pole rows)")
    lines.append("compile: * = served from the persistent cache; B/env = training carry (env state + Q-table + "
                 "records) per env; published = a peer's own figure on another machine (its hardware named), never in "
                 "a ratio")
    plans = list(dict.fromkeys(r["execution_plan"] for r in rows if r.get("execution_plan")))
    if plans:
        lines.append("jaxrobo rows ran under " + "; ".join(plans))
    parts = {r.get("part", 0) for r in rows}
    if len(parts) > 1:
        lines.append(f"rows from {len(parts)} runs merged with --append (the JSON's meta.parts has their commands)")
    return "\n".join(lines)


def write_table(rows: list[dict[str, Any]], meta: dict[str, Any], path: str) -> None:
    """The stdout table as plain text beside the JSON (``throughput.txt``), headed by the device and the
    command it was measured with, for a reader without Python or a JSON viewer."""
    head = [f"jaxrobo throughput on {meta.get('device', '?')} ({meta.get('backend', '?')}, "
            f"{meta.get('cpu_count', '?')} CPU cores)",
            "command: " + " ".join(str(a) for a in meta.get("argv") or []), ""]
    with open(path, "w") as f:
        f.write("\n".join([*head, table(rows)]) + "\n")


def replot(path: str, out_dir: str | None) -> int:
    """``--replot``: the table (stdout and ``throughput.txt``) and the figures again from a results JSON alone
    (nothing is measured)."""
    with open(path) as f:
        data = json.load(f)
    _ratios(data["rows"])
    print(table(data["rows"]))
    out_dir = out_dir or os.path.dirname(os.path.abspath(path))
    os.makedirs(out_dir, exist_ok=True)
    write_table(data["rows"], data.get("meta") or {}, os.path.join(out_dir, "throughput.txt"))
    for written in figures.write_figures(data, out_dir):
        print(f"wrote {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
