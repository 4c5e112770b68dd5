"""Sim-to-sim: fly an exported policy in native MuJoCo and compare with the in-JAX evaluation on the same episodes.

    python scripts/sim2sim.py RUN [--policy DIR] [--episodes 100] [--seed 0]

``RUN`` is a finished run of a task with a native port: tabular CartPoleStayUp-v0/-v1 and PPO/SAC CartPoleContinuous-v0
(``envs/cartpole/native.py``), QuadcopterGoto-v1/-v2 and PPO/SAC QuadcopterGotoTwist-v0 (``envs/quadcopter/native.py``),
ArmReach-v0 (``envs/arm/native.py``). ``--policy`` is its export (``jaxrobo export RUN --out DIR``; without it the run
is exported into a temporary directory). The episodes' initial states, goals and obstacles are drawn once, by the JAX
env's reset (:func:`jaxrobo.task.rollout.rollout` with key ``--seed``), and fed to both:

* **JAX**: the run's greedy table on its own backend, ties to the first maximum (``greedy_policy(ties="first")``,
  the rule the export acts by), and with the evaluation's random ties for reference; or a PPO/SAC run's
  deterministic policy;
* **native**: the exported numpy runner (``jaxrobo_policy.py``) on ``mujoco.MjData`` (the C engine, float64), one
  env, the task's observation, action mapping, control period and success test ported to numpy; no JAX call in
  the loop.

Printed: each side's success rate, how many episodes end the same way, how long the two flights take the same
actions (they part where an observation lands in another bin: float32 vs float64 physics, a different integrator
on the closed-form backends), how far the observations are apart before that, and the native loop's speed.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

#: The task modules with a native port, and the port's module and class.
NATIVE = {"envs.cartpole.stay_up": ("envs.cartpole.native", "NativeCartPole"),
          "envs.quadcopter.goto": ("envs.quadcopter.native", "NativeGoto"),
          "envs.quadcopter.goto_v2": ("envs.quadcopter.native", "NativeGoto"),
          "envs.quadcopter.goto_twist": ("envs.quadcopter.native", "NativeGoto"),
          "envs.cartpole.continuous": ("envs.cartpole.native", "NativeCartPole"),
          "envs.arm.reach": ("envs.arm.native", "NativeArm")}


def load_runner(policy_dir: str):
    """The exported numpy runner, imported from the export directory itself."""
    spec = importlib.util.spec_from_file_location("jaxrobo_policy", os.path.join(policy_dir, "jaxrobo_policy.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.Policy.load(policy_dir)


def jax_policies(run_dir: str, runner) -> tuple:
    """The run's spec and its JAX policies: a table's greedy policy with first-maximum ties (``export``: what the
    exported runner does) and with the evaluation's random ties (``evaluation``); a PPO/SAC run's deterministic
    policy through the env's action mapping (``export``)."""
    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import check_saved_discretiser, load_config, load_tables
    from jaxrobo.task.rollout import greedy_policy
    from jaxrobo.training.run import check_tables, spec_from_config
    from jaxrobo.training.trainer import make_discretiser_for

    cfg = load_config(run_dir)
    if runner.kind == "mlp":
        from jaxrobo.interop.brax_env import BraxEnv

        spec = deep.spec_from_config(cfg)
        loaded = deep.load_policy(run_dir)
        return spec, {"export": deep.env_policy(BraxEnv(spec.env), loaded.make_policy, loaded.params)}
    spec = spec_from_config(cfg, check_memory=False)
    saved, disc = load_tables(run_dir), make_discretiser_for(spec.env, spec.config)
    path = os.path.join(run_dir, "qtables.npz")
    check_tables(saved["q"], spec.env, spec.config, path)  # before any program: tables of the run's config, read
    check_saved_discretiser(saved, disc, path)  # through the discretiser they were learnt with
    table = runner.meta.get("table")
    if isinstance(table, bool) or not isinstance(table, int) or not 0 <= table < saved["q"].shape[0]:
        raise ConfigError(f"{path}: the export's table {table!r} is not one of the run's {saved['q'].shape[0]}")
    q = saved["q"][table]
    return spec, {"export": greedy_policy(q, disc, ties="first"), "evaluation": greedy_policy(q, disc)}


def jax_episodes(env, policies: dict, episodes: int, seed: int) -> dict:
    """Each policy's episodes in JAX from the same resets (key ``seed``), and the initial states and task variables
    of those resets, for the native side."""
    import jax

    from jaxrobo.task.rollout import rollout

    key = jax.random.key(seed)
    res = {}
    for name, policy in policies.items():
        out = jax.jit(lambda k: rollout(env, policy, k, episodes, observe=lambda s: s.obs))(key)
        last = out["last"]
        arrived = getattr(last.task, "arrived", None)
        success = (np.asarray(arrived) if arrived is not None
                   else (np.asarray(out["length"]) == env.default_params.max_episode_steps)
                   & ~np.asarray(last.terminated))
        res[name] = {"success": success, "length": np.asarray(out["length"]), "obs": np.asarray(out["trace"]),
                     "actions": np.asarray(out["action"])}
        first = out["first"]
        res["qpos"] = np.asarray(jax.vmap(env.robot.sim.qpos)(first.pipeline_state), np.float64)
        res["qvel"] = np.asarray(jax.vmap(env.robot.sim.qvel)(first.pipeline_state), np.float64)
        res["task"] = jax.tree.map(np.asarray, first.task)
    return res


def native_episodes(env, runner, start: dict, episodes: int) -> tuple[list[dict], float]:
    """Each episode in native MuJoCo from the JAX resets' initial state and task variables; and the loop's
    control steps per second."""
    import jax  # only to slice the task pytree, before the loop

    module, name = NATIVE[type(env).__module__]
    sim = getattr(importlib.import_module(module), name)(env)
    tasks = [jax.tree.map(lambda x: x[i], start["task"]) for i in range(episodes)]  # host arrays, per episode
    out, steps, t0 = [], 0, time.perf_counter()
    for i in range(episodes):
        ep = sim.episode(runner, start["qpos"][i], start["qvel"][i], tasks[i])
        steps += ep["length"]
        out.append(ep)
    return out, steps / (time.perf_counter() - t0)


#: Continuous actions: the two sides' flights "part" where their actions differ by more than this (of [-1, 1]).
ACTION_GAP = 1e-3
#: Steps at which :func:`compare` reports the largest observation gap over the flights not yet parted there.
GAP_STEPS = (1, 10, 50)
#: Continuous actions: the runner matches JAX's action on JAX's observation within this (tests/test_export.py).
RUNNER_TOL = 1e-5


def compare(jx: dict, native: list[dict], runner) -> dict:
    """Outcome agreement, the step where the action sequences part (continuous actions: differ by more than
    :data:`ACTION_GAP`), the observation gap before it, and the exported runner on JAX's own observations (must
    pick JAX's actions: the round trip; continuous: within :data:`RUNNER_TOL`)."""
    ref = jx["export"]
    n = len(native)
    continuous = runner.kind == "mlp"
    same_outcome = sum(bool(ref["success"][i]) == bool(native[i]["success"]) for i in range(n))
    part, gaps, agree, total = [], [], 0, 0
    at = {k: [] for k in GAP_STEPS}  # the observation gap at step k, in episodes whose flights have not parted by k
    for i in range(n):
        a_j, a_n = ref["actions"][i, : ref["length"][i]], native[i]["actions"]
        m = min(len(a_j), len(a_n))
        differs = (np.abs(a_j[:m] - a_n[:m]).reshape(m, -1).max(axis=1) > ACTION_GAP if continuous
                   else a_j[:m] != a_n[:m])
        diff = np.nonzero(differs)[0]
        if diff.size or len(a_j) != len(a_n):
            k = int(diff[0]) if diff.size else m
            part.append(k)
        else:
            k = m
        # observations 0..k were seen by both sides, after the same actions
        gaps.append(np.max(np.abs(native[i]["obs"][: k + 1] - ref["obs"][i, : k + 1])))
        for step in GAP_STEPS:
            if step <= k and step < len(native[i]["obs"]):
                at[step].append(float(np.max(np.abs(native[i]["obs"][step] - ref["obs"][i, step]))))
        seen = ref["obs"][i, : ref["length"][i]]
        mine = runner.batch(seen)
        agree += int(np.sum(np.abs(mine - a_j).reshape(len(a_j), -1).max(axis=1) <= RUNNER_TOL if continuous
                            else mine == a_j))
        total += len(a_j)
    return {"same_outcome": same_outcome, "identical_flights": n - len(part),
            "median_part_step": float(np.median(part)) if part else None,
            "max_obs_gap_before_parting": float(np.max(gaps)), "runner_on_jax_obs": (agree, total),
            "parted_at": part, "max_obs_gap_at_step": {str(k): max(v) if v else None for k, v in at.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", metavar="RUN")
    ap.add_argument("--policy", default=None, help="the run's export (default: export into a temporary directory)")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=12345, help="key of the episodes' resets (fresh: not the run's seed)")
    ap.add_argument("--json", default=None, metavar="FILE",
                    help="also write the figures printed, and each episode's outcome and length on each side, here")
    args = ap.parse_args(argv)

    from jaxrobo.core.config import ConfigError
    from jaxrobo.export import export_run

    if args.episodes < 1:
        print("sim2sim: --episodes must be >= 1", file=sys.stderr)
        return 2
    tmp = None
    try:
        if args.policy is None:
            tmp = tempfile.TemporaryDirectory()
            args.policy = tmp.name
            export_run(args.run_dir, args.policy)
        runner = load_runner(args.policy)
        spec, policies = jax_policies(args.run_dir, runner)
        if type(spec.env).__module__ not in NATIVE:
            raise ConfigError(f"{spec.env_id}: no native port (have: {', '.join(sorted(NATIVE))})")
        if runner.meta["env_id"] != spec.env_id:
            raise ConfigError(f"{args.policy}: exported from {runner.meta['env_id']}, the run is {spec.env_id}")
    except (ConfigError, FileNotFoundError, ValueError) as err:
        print(f"sim2sim: {err}", file=sys.stderr)
        return 2
    env = spec.env
    what = f"table {runner.meta['table']}" if runner.kind == "tabular" else f"{runner.meta['agent']} MLP"
    print(f"{spec.env_id} ({getattr(env.options, 'backend', '?')} in JAX, float32; native MuJoCo "
          f"{__import__('mujoco').__version__}, float64) · {what} · {args.episodes} episodes, resets from key "
          f"{args.seed}")
    jx = jax_episodes(env, policies, args.episodes, args.seed)
    native, sps = native_episodes(env, runner, jx, args.episodes)
    c = compare(jx, native, runner)
    rate = lambda s: float(np.mean(s))  # noqa: E731
    line = "success  JAX " + (f"{rate(jx['export']['success']):.3f}" if runner.kind == "mlp" else
                              f"first-max ties {rate(jx['export']['success']):.3f} · JAX random ties "
                              f"{rate(jx['evaluation']['success']):.3f}")
    print(f"{line} · native MuJoCo {rate([e['success'] for e in native]):.3f}")
    native_length = np.mean([e["length"] for e in native])
    print(f"mean length  JAX {np.mean(jx['export']['length']):.1f} · native {native_length:.1f}")
    same = "identical" if runner.kind == "tabular" else f"within {ACTION_GAP:g}:"
    print(f"same outcome in {c['same_outcome']}/{args.episodes} episodes; {same} action sequences in "
          f"{c['identical_flights']}/{args.episodes}; where they part, the median step is {c['median_part_step']}")
    print(f"largest observation gap before the flights part: {c['max_obs_gap_before_parting']:.3g}")
    agree, total = c["runner_on_jax_obs"]
    print(f"exported runner on JAX's observations: {agree}/{total} actions "
          + ("identical" if runner.kind == "tabular" else f"within {RUNNER_TOL:g}"))
    print(f"native loop: {sps:,.0f} control steps/s (one env, policy included)")
    if args.json:
        sides = {"native": {"success": [bool(e["success"]) for e in native],
                            "length": [int(e["length"]) for e in native]}}
        for name in ("export", "evaluation"):
            if name in jx:
                sides[f"jax_{name}"] = {"success": [bool(x) for x in jx[name]["success"]],
                                        "length": [int(x) for x in jx[name]["length"]]}
        out = {"env_id": spec.env_id, "policy": what, "kind": runner.kind, "episodes": args.episodes,
               "seed": args.seed, "backend": getattr(env.options, "backend", None),
               "native_control_steps_per_s": sps, **c, "sides": sides}
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
