"""The exported policies in native MuJoCo and through ROS 1: the commands of docs/real_robot.md ("5. Fly in native
MuJoCo") and docs/ros.md ("What was measured"), run as a user runs them, with their figures kept.

Every command is one fresh process (``python -m jaxrobo.cli ...``, ``python scripts/sim2sim.py ...``,
``python -m jaxrobo_ros.policy_node ...``) in a scratch folder (``--work``; a temporary one by default):

* the runs: ``jaxrobo train`` of each page's policies (:data:`RUNS`; docs/real_robot.md's
  ``QuadcopterGoto-v2`` run is docs/ros.md's ``--seed 0`` run: the default seed is 0, one run serves both), each
  exported with ``jaxrobo export RUN --out RUN_policy``;
* sim2sim (:data:`SIM2SIM`): ``python scripts/sim2sim.py RUN --policy RUN_policy --episodes N [--seed S]`` with
  ``--json``: each side's outcome and length per episode, the agreement figures the script prints;
* ROS (:data:`ROS`), where ROS 1 is there: a master on a free port of localhost (``roscore``, as
  ``tests/test_ros.py`` starts it), then for each row ``jaxrobo ros sim EXPORT --episodes N [--lockstep] [--speed
  X] --seed S --results FILE`` beside ``python -m jaxrobo_ros.policy_node EXPORT``, compared episode by episode
  with the sim2sim row of the same policy and resets. Without rospy or roscore the ROS rows are kept as
  ``skipped`` with the reason.

    python benchmarks/ros_sim2sim.py                      # every row, the pages' episode counts (minutes on 2 cores)
    python benchmarks/ros_sim2sim.py --episodes 4 --no-ros --out /tmp/x.json   # a smoke run

Writes ``ros_sim2sim.json`` under ``benchmarks/results/<device>/`` (``--out`` for another path).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import ROOT, free_port, git_commit, write_json  # noqa: E402

#: The runs, by name: their ``jaxrobo train`` flags (the pages' commands; ``--no-progress`` added).
RUNS = {
    "cartpole": ["--env", "CartPoleStayUp-v0", "--agent", "qlearn", "--n-envs", "16"],
    "goto2": ["--env", "QuadcopterGoto-v2", "--seed", "0"],
    "arm": ["--env", "ArmReach-v0"],
    "cp_ppo": ["--env", "CartPoleContinuous-v0", "--agent", "ppo", "--set", "num_timesteps=400000", "--n-envs", "256",
               "--set", "batch_size=256", "--set", "num_minibatches=8", "--set", "num_evals=3", "--set",
               "eval_episodes=32"],
    "cp": ["--env", "CartPoleStayUp-v0", "--n-envs", "64", "--nepisodes", "200", "--seed", "0"],
}
#: What a train row keeps of the run's summary.json.
SUMMARY = ("env_steps", "target_met_in_training", "learning_target", "eval_success_rate", "eval_mean_length",
           "eval_best_table")
#: sim2sim rows: (page, run, episodes, reset key or None for the script's default 12345, export given).
SIM2SIM = (
    ("real_robot", "cartpole", 100, None, True),
    ("real_robot", "goto2", 200, None, True),
    ("real_robot", "arm", 200, None, True),
    ("real_robot", "cp_ppo", 100, None, False),  # the page's command: the script exports into a temporary folder
    ("ros", "goto2", 100, 12345, True),
    ("ros", "cp", 20, 3, True),
)
#: ROS rows: (name, run, episodes, reset key, sim flags); each compared with the ``ros`` sim2sim row of its run.
ROS = (
    ("goto2_lockstep", "goto2", 100, 12345, ["--lockstep"]),
    ("cp_lockstep", "cp", 20, 3, ["--lockstep"]),
    ("goto2_speed10", "goto2", 50, 12345, ["--speed", "10"]),
)


def run(cmd: list[str], env: dict, log: str, timeout: float) -> dict[str, Any]:
    """One fresh process, its output to ``log``; its exit code and wall seconds."""
    t0 = time.perf_counter()
    with open(log, "w") as out:
        try:
            rc = subprocess.run(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                                timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            rc = None
    return {"exit_code": rc, "wall_seconds": round(time.perf_counter() - t0, 2)}


def tail(path: str, n: int = 1500) -> str:
    with open(path) as f:
        return f.read()[-n:]


def shrunk(episodes: int, cap: int | None) -> int:
    return episodes if cap is None else min(episodes, cap)


def ros_reason() -> str | None:
    """Why ROS rows cannot run here (None: they can)."""
    try:
        from jaxrobo_ros.system import unavailable_reason
    except ImportError as err:
        return f"jaxrobo_ros does not import: {err}"
    reason = unavailable_reason()
    if reason:
        return reason
    return None if shutil.which("roscore") else "roscore is not on PATH: apt-get install ros-core (docs/ros.md)"


def compare_ros(eps: list[dict], sides: dict[str, dict]) -> dict[str, Any]:
    """A ROS row's episodes against other flights of the same resets (``sides``: each side's ``success`` and
    ``length`` per episode): the sim2sim row's native and JAX sides, and a lockstep ROS row's."""
    n = len(eps)
    steps = [e["steps"] for e in eps]
    success = [bool(e["success"]) for e in eps]
    out: dict[str, Any] = {"episodes_flown": n, "success_rate": sum(success) / n if n else None,
                           "successes": sum(success), "mean_steps": sum(steps) / n if n else None}
    for side, s in sides.items():
        out[f"same_outcome_as_{side}"] = sum(a == b for a, b in zip(success, s["success"]))
        out[f"same_steps_as_{side}"] = sum(a == b for a, b in zip(steps, s["length"]))
        out[f"{side}_success_rate_same_episodes"] = sum(s["success"][:n]) / n if n else None
        # (episode, steps here, steps there) of each episode flown for another number of steps
        out[f"steps_differ_from_{side}"] = [(i, a, b) for i, (a, b) in enumerate(zip(steps, s["length"])) if a != b]
    out["steps"] = steps
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=None,
                    help="at most this many episodes a row (a smoke run; default: the pages' counts)")
    ap.add_argument("--no-ros", action="store_true", help="leave the ROS rows out (kept as skipped)")
    ap.add_argument("--runs", default=",".join(RUNS), help="the runs to train and fly (comma-separated names)")
    ap.add_argument("--work", default=None, help="scratch folder for the runs and logs (default: a temporary one)")
    ap.add_argument("--out", default=None, help="output JSON (default benchmarks/results/<device>/ros_sim2sim.json)")
    ap.add_argument("--timeout", type=float, default=900, help="wall-clock bound on any one command, s")
    args = ap.parse_args(argv)
    names = [r for r in args.runs.split(",") if r]
    unknown = sorted(set(names) - set(RUNS))
    if unknown:
        ap.error(f"--runs: unknown {', '.join(unknown)} (have: {', '.join(RUNS)})")

    work = args.work or tempfile.mkdtemp(prefix="ros_sim2sim_")
    os.makedirs(work, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    env.setdefault("JAX_PLATFORMS", "cpu")
    me = [sys.executable, "-m", "jaxrobo.cli"]
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()

    trained: dict[str, str] = {}
    for name in names:
        out = os.path.join(work, name)
        cmd = me + ["train", *RUNS[name], "--no-progress", "--out", out]
        r = run(cmd, env, os.path.join(work, f"train_{name}.log"), args.timeout)
        row = {"kind": "train", "run": name, "command": " ".join(["jaxrobo"] + cmd[3:]).replace(work, "runs"), **r}
        if r["exit_code"] == 0:
            with open(os.path.join(out, "summary.json")) as f:
                summary = json.load(f)
            row.update({k: summary[k] for k in SUMMARY if k in summary})
            e = run(me + ["export", out, "--out", out + "_policy"], env, os.path.join(work, f"export_{name}.log"),
                    args.timeout)
            row["export_exit_code"] = e["exit_code"]
            if e["exit_code"] == 0:
                trained[name] = out
        else:
            row["log_tail"] = tail(os.path.join(work, f"train_{name}.log"))
        rows.append(row)
        print(f"train {name}: exit {row['exit_code']}, {row['wall_seconds']} s", flush=True)

    refs: dict[tuple[str, str], dict] = {}
    for page, name, episodes, seed, given in SIM2SIM:
        if name not in names:
            continue
        n = shrunk(episodes, args.episodes)
        row: dict[str, Any] = {"kind": "sim2sim", "page": page, "run": name, "episodes": n,
                               "seed": 12345 if seed is None else seed}
        if name not in trained:
            rows.append({**row, "status": "skipped", "reason": f"the run {name} did not train or export"})
            continue
        path = os.path.join(work, f"sim2sim_{page}_{name}.json")
        flags = (["--policy", trained[name] + "_policy"] if given else []) + ["--episodes", str(n)]
        flags += [] if seed is None else ["--seed", str(seed)]
        cmd = [sys.executable, os.path.join("scripts", "sim2sim.py"), trained[name], *flags]
        r = run(cmd + ["--json", path], env, os.path.join(work, f"sim2sim_{page}_{name}.log"), args.timeout)
        row["command"] = " ".join(["python", "scripts/sim2sim.py", f"runs/{name}", *flags]).replace(
            trained[name] + "_policy", f"runs/{name}_policy")
        row.update(r)
        if r["exit_code"] != 0:
            rows.append({**row, "status": "failed", "reason": tail(os.path.join(work, f"sim2sim_{page}_{name}.log"))})
            continue
        with open(path) as f:
            got = json.load(f)
        refs[(page, name)] = got
        sides = got.pop("sides")
        got["policy_kind"] = got.pop("kind")
        got.update({f"max_obs_gap_at_step_{k}": v for k, v in got.pop("max_obs_gap_at_step").items()})
        row.update(status="ok", **{k: v for k, v in got.items() if k not in ("episodes", "seed")})
        for side, s in sides.items():
            row[f"{side}_success_rate"] = sum(s["success"]) / n
            row[f"{side}_successes"] = sum(s["success"])
            row[f"{side}_mean_length"] = sum(s["length"]) / n
        row["steps_jax_export"] = sum(sides["jax_export"]["length"])
        got["sides"] = row["sides"] = sides
        rows.append(row)
        print(f"sim2sim {page} {name}: {n} episodes, same outcome {row['same_outcome']}, identical "
              f"{row['identical_flights']}, {row['wall_seconds']} s", flush=True)

    reason = "left out (--no-ros)" if args.no_ros else ros_reason()
    master = None
    if reason is None:
        from jaxrobo.ros.launch import ros_env, start_master, stop

        port = free_port()
        renv = ros_env(port)
        renv.update(env, ROS_MASTER_URI=renv["ROS_MASTER_URI"], ROS_HOSTNAME="127.0.0.1",
                    ROS_LOG_DIR=os.path.join(work, "roslog"), ROS_HOME=work)
        try:
            master = start_master(port, renv)
        except RuntimeError as err:
            reason = str(err)
    flown: dict[tuple[str, str], dict] = {}  # the lockstep ROS rows' episodes, by run
    try:
        for name, run_name, episodes, seed, flags in ROS:
            if run_name not in names:
                continue
            n = shrunk(episodes, args.episodes)
            row = {"kind": "ros", "name": name, "run": run_name, "episodes": n, "seed": seed,
                   "mode": "lockstep" if "--lockstep" in flags else f"{flags[-1]} x real time"}
            ref = refs.get(("ros", run_name))
            if reason is not None:
                rows.append({**row, "status": "skipped", "reason": f"ROS 1: {reason}"})
                continue
            if ref is None:
                rows.append({**row, "status": "skipped", "reason": f"no sim2sim row of {run_name} to compare with"})
                continue
            export = trained[run_name] + "_policy"
            results = os.path.join(work, f"ros_{name}.json")
            sim_flags = ["--episodes", str(n), *flags, "--seed", str(seed)]
            row["command"] = (f"jaxrobo ros sim runs/{run_name}_policy {' '.join(sim_flags)} --results {name}.json"
                              f" & python -m jaxrobo_ros.policy_node runs/{run_name}_policy")
            plog = open(os.path.join(work, f"ros_{name}_policy.log"), "w")
            slog = os.path.join(work, f"ros_{name}_sim.log")
            t0 = time.perf_counter()
            # The policy node first: without --lockstep the sim steps on at once, with or without a command
            policy = subprocess.Popen([sys.executable, "-m", "jaxrobo_ros.policy_node", export], env=renv, cwd=ROOT,
                                      stdout=plog, stderr=subprocess.STDOUT, start_new_session=True)
            with open(slog, "w") as out:
                sim = subprocess.Popen(me + ["ros", "sim", export, *sim_flags, "--results", results], env=renv,
                                       cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
                try:
                    rc = sim.wait(timeout=args.timeout)
                except subprocess.TimeoutExpired:
                    rc = None
            row["wall_seconds"] = round(time.perf_counter() - t0, 2)
            stop([sim, policy])
            plog.close()
            row["exit_code"] = rc
            if rc != 0 or not os.path.exists(results):
                rows.append({**row, "status": "failed", "reason": tail(slog)})
                continue
            with open(results) as f:
                eps = json.load(f)["episodes"]
            sides = dict(ref["sides"])
            if "--lockstep" not in flags and (run_name, "lockstep") in flown:
                sides["ros_lockstep"] = flown[(run_name, "lockstep")]
            row.update(status="ok", **compare_ros(eps, sides))
            if "--lockstep" in flags:
                flown[(run_name, "lockstep")] = {"success": [bool(e["success"]) for e in eps],
                                                 "length": [e["steps"] for e in eps]}
            with open(slog) as f:
                row["sim_log_tail"] = [line[-300:] for line in f.read().strip().splitlines()[-3:]]
            rows.append(row)
            print(f"ros {name}: success {row['success_rate']:.3f}, same steps as native "
                  f"{row['same_steps_as_native']}/{n}, {row['wall_seconds']} s", flush=True)
    finally:
        if master is not None:
            stop([master])

    import jax  # the device's name, after the children have run

    from _common import device_name
    note = ("Each command a fresh process on this machine, in the order of the rows; docs/real_robot.md's "
            "QuadcopterGoto-v2 run (its default seed, 0) is docs/ros.md's --seed 0 run, trained once. sim2sim rows: "
            "scripts/sim2sim.py's figures (same_outcome, identical_flights: JAX with first-maximum ties against native "
            "MuJoCo; runner_on_jax_obs: the exported runner's actions on JAX's observations, identical or, for an "
            "MLP, within 1e-5; max_obs_gap_at_step: the largest observation gap at that step over the flights not "
            "yet parted). ROS rows: the sim node and the policy node on a master of localhost, each episode against "
            "the sim2sim row of the same policy and resets (page ros): same outcome and same number of steps as "
            "native in-process and as JAX, and (at 10 x real time) as the lockstep row's first episodes; "
            "steps_differ_from_*: (episode, steps here, steps there). sides: each sim2sim side's outcome and length "
            "per episode.")
    if args.episodes is not None:
        note += f" Shrunk: at most {args.episodes} episodes a row (not the pages' counts)."
    out = {"benchmark": "ros_sim2sim", "device": device_name(), "jax": jax.__version__,
           "mujoco": __import__("mujoco").__version__,
           "code": git_commit("envs", "agents", "jaxrobo_ros", "scripts", "benchmarks/ros_sim2sim.py"),
           "command": " ".join(["python", "benchmarks/ros_sim2sim.py", *(argv if argv is not None else sys.argv[1:])]),
           "ros": reason or "rospy and roscore found", "wall_seconds": round(time.perf_counter() - t_start, 1),
           "note": note, "rows": rows}
    path = write_json(out, args.out, "ros_sim2sim.json")
    print(f"wrote {path}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if all(r.get("status", "ok") in ("ok", "skipped") and r.get("exit_code", 0) == 0
                    for r in rows if r.get("status") != "skipped") else 1


if __name__ == "__main__":
    sys.exit(main())
