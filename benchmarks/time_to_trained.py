"""Time to a trained robot: each shipped task's default ``jaxrobo train --env ID``, as a user runs it.

Every row is one fresh process of the command (``python -m jaxrobo.cli train --env ID [--agent ppo] --seed S
--no-progress``), timed from start to exit, with an empty compile cache (``cold``: a new ``JAXROBO_CACHE_DIR``) and
again with that cache filled (``warm``). The wall is split with the run's own ``summary.json``: compile, run (training,
the learning-target checks included), evaluation, writing, start-up (interpreter, imports, device discovery, config:
the process's age when training starts) and the rest (the exit), and the row keeps the env steps it took and its
learning figure (the figure the task's learning target is judged by, on the final evaluation's fresh episodes).

    python benchmarks/time_to_trained.py                       # every task, seed 0, cold then warm
    python benchmarks/time_to_trained.py --seeds 16 --warm-only --envs QuadcopterGoto-v2
    python benchmarks/time_to_trained.py --set n_envs=1024     # the same with an override (exploring defaults)
    python benchmarks/time_to_trained.py --envs CartPoleContinuous-v0 --peers --seeds 3   # beside Brax's own

``--peers`` adds, after the tasks, a peer measured the same way on the same device: Brax's PPO on Brax's own
``inverted_pendulum`` (the nearest peer of ``CartPoleContinuous-v0``: a cart-pole, 1 reward a step, episodes of
1,000 steps) with the settings Brax's training notebook gives it (:data:`BRAX_PENDULUM`: 2 M env steps, 20
evaluations), one fresh process per row, started as a user starts it, with the same empty or filled compile cache.
Brax's trainer runs its whole budget, so its row also says when its own evaluation first reached the target's
return (``target_met_at_seconds`` from the start, ``target_met_at_steps``). Brax 0.14's trainer needs two JAX calls
that JAX 0.10 removed; the peer's process gets them from :func:`jaxrobo.interop.brax_compat.install_jax_compat`.

Writes ``time_to_trained.json`` under ``--out`` (default ``benchmarks/results/local/<device>/``).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from typing import Any

#: The shipped tasks and the learner their default command uses (``--agent`` for a Box-action task).
TASKS = (("CartPoleStayUp-v0", None), ("QuadcopterGoto-v2", None), ("ArmReach-v0", None),
         ("CartPoleContinuous-v0", "ppo"), ("QuadcopterGotoTwist-v0", "ppo"))

#: Published anchors: what users compare with, with the hardware their authors name. Only figures we could
#: trace to their source carry a number (``at_most``: the source gives a bound, "under a minute"); the others say
#: what their authors claim.
ANCHORS = (
    {"what": "L2F (RLtools, 'Learning to Fly in Seconds'): a quadrotor control policy trained", "seconds": 18.0,
     "hardware": "a consumer laptop (the paper's figure)"},
    {"what": "Aerial Gym Simulator: a quadrotor position-setpoint policy (rl_games PPO, 8,192 envs) trained",
     "seconds": 60.0, "at_most": True,
     "hardware": "one NVIDIA RTX 3090 (ntnu-arl/aerial_gym_simulator, docs/6_rl_training.md: 'under a minute')"},
    {"what": "PureJaxRL: PPO on gymnax CartPole-v1", "seconds": None,
     "hardware": "one GPU; its README claims over 1000x the speed of PyTorch baselines, no time-to-trained figure"},
)


#: Brax's training notebook's PPO settings for its ``inverted_pendulum`` ("reasonable hyperparameters" its authors
#: determined offline), and the notebook's physics backend.
BRAX_PENDULUM = dict(num_timesteps=2_000_000, num_evals=20, reward_scaling=10, episode_length=1000,
                     normalize_observations=True, action_repeat=1, unroll_length=5, num_minibatches=32,
                     num_updates_per_batch=4, discounting=0.97, learning_rate=3e-4, entropy_cost=1e-2, num_envs=2048,
                     batch_size=1024, seed=1)
BRAX_BACKEND = "positional"
#: The return the peer's evaluation must reach to count as trained: CartPoleContinuous-v0's target (a mean greedy
#: episode of at least 500 of its 1,000 steps), in the pendulum's reward of 1 a step.
BRAX_TARGET_RETURN = 500.0


def peer_child(launched: float, overrides: dict[str, Any]) -> None:
    """The peer's process: Brax's PPO on its ``inverted_pendulum`` with :data:`BRAX_PENDULUM` (and ``overrides``);
    prints one JSON line (each evaluation's step, return and seconds since ``launched``, the parent's clock at the
    start)."""
    from jaxrobo.speed import cache

    cache.enable_compilation_cache()  # $JAXROBO_CACHE_DIR, as for jaxrobo's own rows
    from jaxrobo.interop import brax_compat

    brax_compat.install_jax_compat()
    import brax.envs
    from brax.training.agents.ppo import train as ppo

    settings = {**BRAX_PENDULUM, **overrides}
    evals: list[tuple[int, float, float]] = []

    def progress(step: int, metrics: dict[str, Any]) -> None:
        evals.append((int(step), float(metrics.get("eval/episode_reward", float("nan"))), time.time() - launched))

    ppo.train(environment=brax.envs.get_environment("inverted_pendulum", backend=BRAX_BACKEND),
              progress_fn=progress, **settings)
    print("PEER" + json.dumps({"evals": evals, "settings": settings, "backend": BRAX_BACKEND}), flush=True)


def peer_once(cache: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """One fresh process of :func:`peer_child`, timed from start to exit as :func:`run_once` times a command."""
    cmd = [sys.executable, os.path.abspath(__file__), "--peer-child", repr(time.time()), "--peer-settings",
           json.dumps(overrides)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env={**os.environ, "JAXROBO_CACHE_DIR": cache}, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    changed = ", ".join(f"{k}={v}" for k, v in overrides.items())
    row: dict[str, Any] = {"env_id": "brax:inverted_pendulum",
                           "agent": "ppo (Brax's notebook settings" + (f"; changed: {changed})" if changed else ")"),
                           "seed": overrides.get("seed", BRAX_PENDULUM["seed"]), "set": [],
                           "wall_seconds": round(wall, 3),
                           "exit_code": proc.returncode}
    line = next((x for x in proc.stdout.splitlines() if x.startswith("PEER")), None)
    if proc.returncode != 0 or line is None:
        row["error"] = (proc.stderr or proc.stdout)[-2000:]
        return row
    got = json.loads(line[4:])
    evals = got["evals"]
    met = next((e for e in evals if e[1] >= BRAX_TARGET_RETURN), None)
    row.update({"env_steps": evals[-1][0] if evals else 0, "learning_figure": "eval/episode_reward (Brax's)",
                "learning_value": evals[-1][1] if evals else None,
                "learning_target": f"evaluation return >= {BRAX_TARGET_RETURN:g}",
                "target_met_at_steps": None if met is None else met[0],
                "target_met_at_seconds": None if met is None else round(met[2], 3),
                "evals": evals, "settings": got["settings"], "backend": got["backend"]})
    return row


def learning_figure(summary: dict[str, Any]) -> tuple[str, float | None]:
    """The figure a run's learning target is judged by, from its ``summary.json``: ``(name, value)``."""
    for key in ("selected_table_fresh_mean_length", "eval_best_table_success_rate", "final_eval_success_rate",
                "final_eval_mean_length", "eval_best_table_mean_length"):
        if key in summary:
            return key, float(summary[key])
    return "none", None


def run_once(env_id: str, agent: str | None, seed: int, cache: str, sets: list[str], work: str) -> dict[str, Any]:
    out = os.path.join(work, f"{env_id}_{seed}_{time.monotonic_ns()}")
    cmd = [sys.executable, "-m", "jaxrobo.cli", "train", "--env", env_id, "--seed", str(seed), "--no-progress",
           "--out", out]
    if agent:
        cmd += ["--agent", agent]
    for s in sets:
        cmd += ["--set", s]
    env = {**os.environ, "JAXROBO_CACHE_DIR": cache}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    row: dict[str, Any] = {"env_id": env_id, "agent": agent or "preset", "seed": seed, "set": sets,
                           "wall_seconds": round(wall, 3), "exit_code": proc.returncode}
    path = os.path.join(out, "summary.json")
    if proc.returncode != 0 or not os.path.isfile(path):
        row["error"] = (proc.stderr or proc.stdout)[-2000:]
        return row
    with open(path) as f:
        s = json.load(f)
    parts = {"startup": s.get("startup_seconds"), "compile": s.get("compile_seconds"),
             "run": s.get("run_seconds", s.get("train_seconds")),
             "evaluation": s.get("eval_seconds"),
             "writing": None if s.get("write_seconds") is None  # the results and the closing checkpoint
             else s["write_seconds"] + s.get("checkpoint_seconds", 0.0)}
    if agent:  # a ppo/sac run's train_seconds counts its compile; its evaluations are apart
        parts["compile"] = None
    known = sum(v for v in parts.values() if v is not None)
    name, value = learning_figure(s)
    row.update({f"{k}_seconds": v for k, v in parts.items()})
    row["rest_seconds"] = round(wall - known, 3)  # start-up where the run did not measure it, and the exit
    row.update({"env_steps": s.get("env_steps"), "learning_figure": name, "learning_value": value,
                "learning_target": s.get("learning_target"), "target_met_in_training": s.get("target_met_in_training"),
                "n_envs": s.get("n_envs", s.get("num_envs")), "stdout_tail": proc.stdout[-600:]})
    return row


def collect(tasks: list[tuple[str, str | None]], seeds: int = 1, cold: bool = True, sets: list[str] | None = None,
            report: Any = None, peers: bool = False,
            peer_overrides: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The rows of ``tasks`` (``(env_id, agent)``): per task a cold row (seed 0, an empty cache) unless not
    ``cold`` (the cache then filled by an untimed run), then ``seeds`` warm rows; ``report(row)`` after each. With
    ``peers``, the same for Brax's ``inverted_pendulum`` (:func:`peer_once`; its warm rows repeat its one seed)."""
    rows: list[dict[str, Any]] = []

    def add(row: dict[str, Any]) -> None:
        rows.append(row)
        if report is not None:
            report(row)

    with tempfile.TemporaryDirectory(prefix="jaxrobo-ttt-") as work:
        for env_id, agent in tasks:
            cache = tempfile.mkdtemp(prefix="cache-", dir=work)
            first = run_once(env_id, agent, 0, cache, sets or [], work)
            if cold:
                add({**first, "cache": "cold"})
            for seed in range(seeds):
                add({**run_once(env_id, agent, seed, cache, sets or [], work), "cache": "warm"})
        if peers:
            cache = tempfile.mkdtemp(prefix="cache-", dir=work)
            first = peer_once(cache, peer_overrides or {})
            if cold:
                add({**first, "cache": "cold"})
            for _ in range(seeds):
                add({**peer_once(cache, peer_overrides or {}), "cache": "warm"})
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table of the rows: the wall and its split, env steps and the learning figure."""
    head = ("task", "learner", "cache", "wall s", "start-up", "compile", "run", "eval", "write", "env steps", "learned")
    lines = [" | ".join(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['env_id']} | {r['agent']} | {r['cache']} | failed (exit {r['exit_code']})")
            continue
        cell = lambda k: "-" if r.get(k) is None else f"{r[k]:.1f}"  # noqa: E731
        learned = f"{r['learning_figure']} {r['learning_value']:.3g}"
        if "target_met_at_seconds" in r:
            learned += f" (target at {cell('target_met_at_seconds')} s)"
        lines.append(" | ".join((r["env_id"], r["agent"], r["cache"], f"{r['wall_seconds']:.1f}",
                                 cell("startup_seconds"), cell("compile_seconds"), cell("run_seconds"),
                                 cell("evaluation_seconds"),
                                 cell("writing_seconds"), f"{r['env_steps']:,}", learned)))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="*", default=None, help="task ids (default: every shipped task)")
    p.add_argument("--seeds", type=int, default=1, help="seeds 0..N-1 of the warm rows (the cold row: seed 0)")
    p.add_argument("--warm-only", action="store_true", help="no cold row (the cache is filled by an untimed run)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed to every command")
    p.add_argument("--out", default=None, help="folder of time_to_trained.json")
    p.add_argument("--peers", action="store_true", help="also Brax's PPO on its inverted_pendulum (see above)")
    p.add_argument("--peer-set", action="append", default=[], metavar="KEY=N",
                   help="one of the peer's settings as a number instead of the notebook's (a smoke run; rows so "
                        "made are not the notebook's peer)")
    p.add_argument("--peer-child", default=None, help=argparse.SUPPRESS)  # the peer's own process (peer_once)
    p.add_argument("--peer-settings", default="{}", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.peer_child is not None:
        peer_child(float(args.peer_child), json.loads(args.peer_settings))
        return 0
    if args.seeds < 1:
        p.error(f"--seeds {args.seeds}: expected an integer >= 1")
    if args.peer_set and not args.peers:
        p.error("--peer-set: only with --peers")
    overrides: dict[str, Any] = {}
    for item in args.peer_set:
        key, _, value = item.partition("=")
        if key not in BRAX_PENDULUM or isinstance(BRAX_PENDULUM[key], bool):
            p.error(f"--peer-set {item}: KEY must be one of the peer's numeric settings "
                    f"({', '.join(k for k, v in BRAX_PENDULUM.items() if not isinstance(v, bool))})")
        kind = type(BRAX_PENDULUM[key])
        try:
            number = kind(value)
        except ValueError:
            p.error(f"--peer-set {item}: expected {'an integer' if kind is int else 'a number'}")
        if not (number > 0 and math.isfinite(number)):
            p.error(f"--peer-set {item}: expected a finite value > 0")
        overrides[key] = number
    import jax

    device = jax.devices()[0].device_kind
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "local",
                                   jax.default_backend())
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "time_to_trained.json")
    tasks = [t for t in TASKS if args.envs is None or t[0] in args.envs]
    done: list[dict[str, Any]] = []

    def report(row: dict[str, Any]) -> None:
        done.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "stdout_tail"}), flush=True)
        with open(path, "w") as f:  # every row so far on disk: a run stopped by a time limit keeps them
            json.dump({"device": device, "backend": jax.default_backend(), "rows": done, "anchors": ANCHORS}, f,
                      indent=1)

    rows = collect(tasks, args.seeds, not args.warm_only, args.set, report, args.peers, overrides)
    print(table(rows))
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
