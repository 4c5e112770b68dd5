"""What a training chunk split over several devices exchanges between them, and what that costs across processes.

A run split over devices (``devices: N``) compiles its chunk as one program XLA partitions, except where each
device's envs step alone (``jaxrobo.training.driver.per_device_chunk``: on GPUs for independent envs). This counts
the collectives in the partitioned chunk of each task, inside its step loop and around it, then (``--processes``)
times the cart-pole's run in one process over 4 CPU devices against two processes of 2 devices each
(``jax.distributed``, Gloo over TCP), as ``tests/test_sharding.py`` runs it.

    JAX_PLATFORMS=cpu XLA_FLAGS=--xla_force_host_platform_device_count=4 \\
        python benchmarks/studies/chunk_collectives.py --processes \\
        --out benchmarks/results/cpu-2cores/chunk_collectives.json
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from _common import ROOT, free_port, write_json  # noqa: E402

COLLECTIVES = ("all-reduce", "all-gather", "reduce-scatter", "collective-permute", "all-to-all")
#: (env id, overrides): each task's default learner set-up at a small batch.
CASES = [("CartPoleStayUp-v0", {"n_envs": 8, "nsteps": 100, "chunk_steps": 50, "stop_at_target": False}),
         ("QuadcopterGoto-v2", {"n_envs": 64}),
         ("ArmReach-v0", {"n_envs": 64})]
#: The run tests/test_sharding.py makes in two processes (200 chunks of 50 steps).
RUN = ["--env", "CartPoleStayUp-v0", "--nepisodes", "100", "--set", "nsteps=100", "--set", "chunk_steps=50",
       "--n-envs", "8", "--set", "stop_at_target=false", "--set", "eval_episodes=10", "--no-progress"]


def computations(hlo: str) -> dict[str, str]:
    """The HLO module's computations by name."""
    out = {}
    for block in re.split(r"\n(?=\S)", hlo):
        m = re.match(r"(?:ENTRY )?(%[\w.\-]+) ", block)
        if m:
            out[m.group(1)] = block
    return out


def reached(comps: dict[str, str], name: str) -> set[str]:
    """``name`` and every computation it calls, directly or not."""
    seen, todo = set(), [name]
    while todo:
        n = todo.pop()
        if n in seen or n not in comps:
            continue
        seen.add(n)
        todo += re.findall(r"(?:calls|to_apply|body|condition)=(%[\w.\-]+)", comps[n])
        for group in re.findall(r"branch_computations=\{([^}]*)\}", comps[n]):
            todo += [c.strip() for c in group.split(",")]
    return seen


def count(text: str) -> dict[str, int]:
    found = {op: len(re.findall(rf" {op}(?:-start)?\(", text)) for op in COLLECTIVES}
    return {op: n for op, n in found.items() if n}


def chunk_collectives(env_id: str, overrides: dict, devices: int) -> dict:
    import jax

    from jaxrobo.tabular.learner import AgentParams
    from jaxrobo.training import driver
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    spec = resolve(env_id, overrides={**overrides, "devices": devices})
    trainer = Trainer(spec.env, spec.config)
    key = jax.random.key(0)
    agent_params, env_params = spec.agent_params or AgentParams(), spec.env.default_params
    with trainer.plan.tracing():
        runner = driver.compiled_init(trainer, key, agent_params, env_params)(key, agent_params, env_params)
        mesh = driver.env_mesh(trainer)
        one_program = mesh is not None and driver.per_device_chunk(trainer, mesh)
        hlo = driver.compiled_chunk(trainer, runner, agent_params, env_params).as_text()
    comps = computations(hlo)
    loops = []
    for cond, body in re.findall(r" while\(.*?condition=(%[\w.\-]+), body=(%[\w.\-]+)", hlo):
        inside = "\n".join(comps[c] for c in reached(comps, body))
        trips = re.search(r'"known_trip_count":\{"n":"(\d+)"', comps.get(body, "") + inside)
        loops.append({"loop": body, "collectives_per_iteration": count(inside),
                      "known_trip_count": int(trips.group(1)) if trips else None})
    return {"env": env_id, "overrides": overrides, "devices": devices, "plan": str(trainer.plan),
            "shared_table": bool(spec.config.shared_table), "one_program_per_device": one_program,
            "collectives_in_program": count(hlo), "loops": loops}


def _run_seconds(out: str) -> float | None:
    """The run's training seconds, from the run directory's ``summary.json`` (None where it did not finish)."""
    try:
        with open(os.path.join(out, "summary.json")) as f:
            return float(json.load(f)["run_seconds"])
    except (OSError, ValueError, KeyError):
        return None


def processes() -> list[dict]:
    """The cart-pole run of tests/test_sharding.py in one process over 4 CPU devices, then in two of 2 each."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT, JAXROBO_CACHE_DIR="off")
    cmd = [sys.executable, "-m", "jaxrobo.cli", "train", *RUN]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        one = subprocess.run(cmd + ["--out", os.path.join(tmp, "one")], cwd=ROOT, text=True, capture_output=True,
                             env=dict(env, XLA_FLAGS="--xla_force_host_platform_device_count=4"), timeout=900)
        rows.append({"processes": 1, "devices_each": 4, "rc": one.returncode,
                     "run_s": _run_seconds(os.path.join(tmp, "one")), "chunks": 200})
        two = dict(env, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAXROBO_NUM_PROCESSES="2",
                   JAXROBO_COORDINATOR=f"localhost:{free_port()}")
        procs = [subprocess.Popen(cmd + ["--out", os.path.join(tmp, "two")], cwd=ROOT, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  env=dict(two, JAXROBO_PROCESS_ID=str(i))) for i in range(2)]
        for p in procs:
            p.communicate(timeout=900)
        rows.append({"processes": 2, "devices_each": 2, "rc": procs[0].returncode,
                     "run_s": _run_seconds(os.path.join(tmp, "two")), "chunks": 200})
    for r in rows:
        r["seconds_per_chunk"] = round(r["run_s"] / r["chunks"], 4) if r["run_s"] is not None else None
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", type=int, default=4, help="devices to split each chunk over (default 4)")
    p.add_argument("--processes", action="store_true", help="also time the cart-pole run in one and two processes")
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args()
    import jax

    if jax.device_count() < args.devices:
        sys.exit(f"--devices {args.devices}: this process sees {jax.device_count()} device(s) "
                 f"(on CPUs set XLA_FLAGS=--xla_force_host_platform_device_count={args.devices})")
    out = {"device": f"{jax.devices()[0].platform} ({os.cpu_count()} cores), {args.devices} devices",
           "jax": jax.__version__, "chunks": [chunk_collectives(e, o, args.devices) for e, o in CASES]}
    for c in out["chunks"]:
        print(f"{c['env']}: {c['plan']}\n  in the program {c['collectives_in_program']}")
        for loop in c["loops"]:
            print(f"  per iteration of {loop['loop']} (trips {loop['known_trip_count']}): "
                  f"{loop['collectives_per_iteration']}")
    if args.processes:
        out["processes"] = processes()
        for r in out["processes"]:
            print(f"{r['processes']} process(es) x {r['devices_each']} devices: rc {r['rc']}, run {r['run_s']} s, "
                  f"{r['seconds_per_chunk']} s a chunk")
    if args.out:
        print("wrote", write_json(out, args.out))


if __name__ == "__main__":
    main()
