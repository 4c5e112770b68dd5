"""Sharded over 4 (forced host) devices, a sweep and a training run give the unsharded numbers.

The sharded training carry is compared bit for bit with the unsharded one; sweep rows are compared through
their per-row metrics (episode counts exactly; means, reduced on the device, to float32 rounding).

XLA_FLAGS must be set before JAX starts, so the check runs in a subprocess; it compiles at a low optimisation
level to stay quick (both sides use the same flags).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import jax, numpy as np
from jaxrobo.speed import sharding
from jaxrobo.training.run import resolve
from jaxrobo.training.sweep import run_sweep
from jaxrobo.training.trainer import Trainer

def leaves(tree):
    return [np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
            for x in jax.tree.leaves(tree)]

out = {"devices": jax.device_count()}
mesh = sharding.make_mesh()
ov = {"n_envs": 4, "nepisodes": 3, "nsteps": 30, "chunk_steps": 40, "backend": "mjx"}  # MJX: the general engine
spec = resolve("CartPoleStayUp-v0", "default", ov, agent="qlearn")
trainer = Trainer(spec.env, spec.config)
init, chunk = jax.jit(trainer.init), jax.jit(trainer.run_chunk)

def plain(alpha, seed):  # the unsharded, unvmapped reference run
    ap = spec.agent_params.replace(alpha=alpha)
    r = init(jax.random.key(seed), ap, spec.env.default_params)
    for _ in range(trainer.max_chunks()):
        r = chunk(r, ap, spec.env.default_params)
        if int(r.episode.min()) >= 3:
            return r

# a sweep of 3 configurations (padded to 4 rows) split over the 4 devices, against unsharded single runs
split = run_sweep("CartPoleStayUp-v0", [{"alpha": 0.1}, {"alpha": 0.3}, {"alpha": 0.6}], [5], overrides=ov,
                  agent="qlearn", mesh=mesh)
ok = []
for row in split.rows:
    r = plain(row["alpha"], 5)
    ok.append(int(np.asarray(r.env_steps).sum()) == row["env_steps"]
              and np.isclose(np.asarray(r.returns, np.float64)[:, -3:].mean(), row["final_return"], rtol=1e-6)
              and np.isclose(np.asarray(r.lengths, np.float64).mean(), row["mean_length"], rtol=1e-6))
out["sweep_rows"], out["sweep_equal"] = len(split.rows), all(ok)

# one training run with its 4 environments split over the 4 devices, against the same unsharded run
st = sharding.ShardedTrainer(trainer, mesh)
ap, ep, key = spec.agent_params, spec.env.default_params, jax.random.key(1)
r1 = chunk(init(key, ap, ep), ap, ep)
r2 = st.run_chunk(st.init(key, ap, ep), ap, ep)
out["train_sharded_over"] = len(r2.agent.q.sharding.device_set)
# A trainer that steps its envs in groups: sharded, each device steps its own envs at once (a copy; the original
# keeps its groups).
grouped = Trainer(spec.env, spec.config.replace(env_group=3, devices=1))  # one device: its own groups
out["groups"] = [grouped.env_group, sharding.ShardedTrainer(grouped, mesh).trainer.env_group]
out["train_equal"] = all(np.array_equal(a, b) for a, b in zip(leaves(r1), leaves(sharding.gather(r2))))
print(json.dumps(out))
"""


@pytest.mark.slow
def test_sharded_equals_unsharded():
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=4 --xla_backend_optimization_level=0"}
    proc = subprocess.run([sys.executable, "-c", CHILD, ROOT], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 4
    assert out["sweep_rows"] == 3 and out["sweep_equal"]
    assert out["train_sharded_over"] == 4 and out["train_equal"]
    assert out["groups"] == [3, None]


def test_padding_and_shardings():
    import numpy as np

    from jaxrobo.speed import sharding

    mesh = sharding.make_mesh()
    assert sharding.padded_size(3, None) == 3
    assert sharding.padded_size(5, mesh) % mesh.devices.size == 0
    padded = sharding.pad_rows({"a": np.arange(3)}, 4)
    assert padded["a"].tolist() == [0, 1, 2, 2]


def test_spmd_options_leave_out_cse_for_several_cpus_only():
    """The passes a program for several devices leaves out are the ones its platform needs: CSE on CPUs, none on
    GPUs (where leaving CSE out is what made two GPUs round differently from one); one device, or no mesh, keeps
    the options as given."""
    import types

    import numpy as np

    from jaxrobo.speed import sharding

    def mesh(platform: str, n: int):
        return types.SimpleNamespace(devices=np.array([types.SimpleNamespace(platform=platform)] * n))

    given = {"xla_disable_hlo_passes": "foo", "other": 1}
    assert sharding.spmd_options(given, None) is given
    assert sharding.spmd_options(given, mesh("cpu", 1)) is given
    assert sharding.spmd_options(given, mesh("cpu", 4)) == {"xla_disable_hlo_passes": "foo,cse", "other": 1}
    assert sharding.spmd_options(None, mesh("cpu", 2)) == {"xla_disable_hlo_passes": "cse"}
    assert sharding.spmd_options(given, mesh("gpu", 2)) is given
    assert sharding.spmd_options(None, mesh("gpu", 4)) is None


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_processes_with_jax_distributed_give_the_single_process_sweep(tmp_path):
    """The multi-host path for real, on one machine: two processes (2 CPU devices each) join through
    ``jax.distributed`` (``JAXROBO_COORDINATOR`` & co.), shard a ``jaxrobo sweep`` over 4 devices and write
    the same CSV as one process does alone. On MJX (the default backend), whose model must live on each
    process's own device."""
    args = [sys.executable, "-m", "jaxrobo.cli", "sweep", "--env", "CartPoleStayUp-v0", "--grid", "alpha=0.1,0.5",
            "--seeds", "2", "--n-envs", "1", "--nepisodes", "3", "--nsteps", "30",
            "--no-plots"]
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2",
               PYTHONPATH=ROOT)
    # The free port can be taken before the coordinator binds it (the suite runs on several workers, beside
    # other programs): process 0 then fails to add it ("Failed to add port to server"), and the pair starts over
    # on another port.
    for attempt in range(3):
        port = _free_port()
        procs = [subprocess.Popen(args + ["--out", str(tmp_path / f"multi{attempt}")], cwd=ROOT, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  env=dict(env, JAXROBO_COORDINATOR=f"localhost:{port}", JAXROBO_NUM_PROCESSES="2",
                                           JAXROBO_PROCESS_ID=str(i)))
                 for i in range(2)]
        first = procs[0].communicate(timeout=600)[0]
        if procs[0].returncode != 0 and "Failed to add port" in first and attempt < 2:
            procs[1].kill()
            procs[1].communicate()
            continue
        logs = [first, procs[1].communicate(timeout=600)[0]]
        break
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    assert "over 4 devices" in logs[0], logs[0][-2000:]
    single = subprocess.run(args + ["--out", str(tmp_path / "single")], cwd=ROOT, text=True, capture_output=True,
                            env=env, timeout=600)
    assert single.returncode == 0, single.stderr[-3000:]
    assert "over 2 devices" in single.stdout
    multi_csv = (tmp_path / f"multi{attempt}" / "sweep.csv").read_text()
    assert multi_csv == (tmp_path / "single" / "sweep.csv").read_text()
    assert len(multi_csv.splitlines()) == 1 + 2 * 2


def _one_line_exit_2(env: dict, timeout: float = 300) -> str:
    """``jaxrobo train`` of a tiny cart-pole run under ``env``: exit 2 with one line on stderr (MJX's notes on its
    optional backends aside), no traceback, no native crash; the line."""
    proc = subprocess.run([sys.executable, "-m", "jaxrobo.cli", "train", "--env", "CartPoleStayUp-v0", "--nepisodes",
                           "2", "--no-progress"], cwd=ROOT, text=True, capture_output=True, timeout=timeout,
                          env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT, **env))
    lines = [ln for ln in proc.stderr.strip().splitlines() if "warp" not in ln]
    assert proc.returncode == 2 and len(lines) == 1, (proc.returncode, proc.stderr[-3000:])
    return lines[0]


@pytest.mark.parametrize("process_id", ["0", "1"])
def test_a_process_that_never_joins_is_one_line_exit_2(process_id):
    """Process 0 whose peer never comes, and process 1 with no coordinator to register with: JAX's join times
    out (``JAXROBO_INIT_TIMEOUT``), which without jaxrobo's callback aborts natively (exit 134)."""
    port = _free_port()
    line = _one_line_exit_2({"JAXROBO_COORDINATOR": f"127.0.0.1:{port}", "JAXROBO_NUM_PROCESSES": "2",
                             "JAXROBO_PROCESS_ID": process_id, "JAXROBO_INIT_TIMEOUT": "1"})
    assert f"JAXROBO_COORDINATOR='127.0.0.1:{port}'" in line and "did not all join within" in line
    assert "JAXROBO_INIT_TIMEOUT=1 s" in line


@pytest.mark.parametrize("family", ["ipv4", "ipv6-only", "reuseport"])
def test_a_coordinator_port_in_use_is_one_line_exit_2(family):
    """A port another program listens on, over IPv4, over IPv6 alone (JAX's service binds both), or with
    SO_REUSEPORT as a gRPC server (another JAX coordinator) binds: JAX's service would then share the port, and its
    peers register with the other program, so the join fails later with a message that blames them."""
    import socket

    if family == "ipv6-only" and not socket.has_ipv6:
        pytest.skip("no IPv6 on this host")
    with socket.socket(socket.AF_INET6 if family == "ipv6-only" else socket.AF_INET, socket.SOCK_STREAM) as taken:
        if family == "ipv6-only":
            taken.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        if family == "reuseport":
            taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        taken.bind(("::" if family == "ipv6-only" else "", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        line = _one_line_exit_2({"JAXROBO_COORDINATOR": f"127.0.0.1:{port}", "JAXROBO_NUM_PROCESSES": "2",
                                 "JAXROBO_PROCESS_ID": "0", "JAXROBO_INIT_TIMEOUT": "1"})
    assert line.endswith(f"JAXROBO_COORDINATOR='127.0.0.1:{port}': port {port} is already in use on this host "
                         "(process 0 serves the coordinator there); choose a free port")


@pytest.mark.slow  # waits for JAXROBO_INIT_TIMEOUT; process 0's refusal is the default tier's
def test_a_coordinator_port_held_by_another_program_is_one_line_exit_2_for_process_1():
    """For process 1 the port is the coordinator's, in use by design: a program there that is not JAX's
    coordinator (it accepts the connection and never answers) ends the join at JAXROBO_INIT_TIMEOUT, in one line."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(4)
        port = taken.getsockname()[1]
        line = _one_line_exit_2({"JAXROBO_COORDINATOR": f"127.0.0.1:{port}", "JAXROBO_NUM_PROCESSES": "2",
                                 "JAXROBO_PROCESS_ID": "1", "JAXROBO_INIT_TIMEOUT": "1"})
    assert line == (f"jaxrobo train: JAXROBO_COORDINATOR='127.0.0.1:{port}': the 2 processes (JAXROBO_NUM_PROCESSES) "
                    "did not all join within JAXROBO_INIT_TIMEOUT=1 s: process 1 could not register with the "
                    "coordinator")


def test_a_signal_to_one_process_of_a_distributed_run_stops_every_process_at_one_chunk(tmp_path):
    """``jaxrobo train`` in two processes (2 CPU devices each) under ``jax.distributed``, SIGINT to process 0 only:
    each decided alone whether to stop (and whether a save was due by its clock), so process 0 gathered its
    checkpoint while process 1 ran the next chunk and both aborted in Gloo ('collective mismatch'), the run left
    'running'. Now the stop is agreed (``driver.agreed_stop``): both stop after the same chunk and exit 130, the run
    is interrupted and resumable, and process 1's line names process 0's run directory, not its private copy."""
    import signal
    import time

    out = tmp_path / "run"
    args = [sys.executable, "-m", "jaxrobo.cli", "train", "--env", "CartPoleStayUp-v0", "--n-envs", "8",
            "--nepisodes", "20000", "--set", "nsteps=100", "--set", "chunk_steps=50", "--set", "stop_at_target=false",
            "--checkpoint-every", "1", "--no-progress", "--out", str(out)]
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2",
               PYTHONPATH=ROOT)
    for attempt in range(3):
        port = _free_port()
        procs = [subprocess.Popen(args, cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  env=dict(env, JAXROBO_COORDINATOR=f"localhost:{port}", JAXROBO_NUM_PROCESSES="2",
                                           JAXROBO_PROCESS_ID=str(i)))
                 for i in range(2)]
        status = out / "status.json"
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and procs[0].poll() is None:
            try:
                if json.loads(status.read_text()).get("chunks_done", 0) >= 2:
                    break
            except (OSError, ValueError):
                pass
            time.sleep(0.2)
        if procs[0].poll() is not None:
            first = procs[0].communicate()[0]
            procs[1].kill()
            procs[1].communicate()
            if "Failed to add port" in first and attempt < 2:
                continue  # the free port was taken before the coordinator bound it (as in the sweep's test)
            raise AssertionError(first[-3000:])
        break
    try:
        procs[0].send_signal(signal.SIGINT)
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert [p.returncode for p in procs] == [130, 130], [log[-3000:] for log in logs]
    saved = json.loads(status.read_text())
    assert saved["status"] == "interrupted" and saved["signal"] == "SIGINT", saved
    assert f"to go on: jaxrobo train --resume {out}" in logs[1], logs[1][-3000:]
    assert "jaxrobo-process-" not in logs[1]


@pytest.mark.slow
# In two processes on CPUs (Gloo over TCP) a chunk of the cart-pole's run takes about 0.24 s here, against 0.03 s in one
# process over 4 devices: 24 chunks, not 200 (which took 247 s of CI's slow tier).
@pytest.mark.parametrize("run", [["--env", "CartPoleStayUp-v0", "--nepisodes", "12", "--set", "nsteps=100",
                                  "--set", "chunk_steps=50"],
                                 ["--env", "QuadcopterGoto-v2", "--total-steps", "16000", "--nepisodes", "20"]],
                         ids=["cartpole", "goto"])
def test_two_processes_train_to_the_end_and_write_the_one_process_run(tmp_path, run):
    """``jaxrobo train`` in two processes (2 CPU devices each) to its end: the closing checkpoint gathered the
    carry in a thread while the evaluation ran its own collectives, in another order in each process (Gloo's
    'collective mismatch', both aborted at the evaluation); Goto-v2's progress read, left by XLA on one local
    device, was stacked per process by the gather (a TypeError before the first chunk, on two H200s too). Now
    both exit 0 and the run's files are the bytes of one process over 4 devices."""
    import numpy as np

    args = [sys.executable, "-m", "jaxrobo.cli", "train", *run, "--n-envs", "8", "--set", "stop_at_target=false",
            "--set", "eval_episodes=10", "--no-progress"]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT)
    two = dict(env, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    for attempt in range(3):
        out = tmp_path / f"multi{attempt}"
        port = _free_port()
        procs = [subprocess.Popen(args + ["--out", str(out)], cwd=ROOT, text=True, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT,
                                  env=dict(two, JAXROBO_COORDINATOR=f"localhost:{port}", JAXROBO_NUM_PROCESSES="2",
                                           JAXROBO_PROCESS_ID=str(i)))
                 for i in range(2)]
        logs = [p.communicate(timeout=600)[0] for p in procs]
        if procs[0].returncode != 0 and "Failed to add port" in logs[0] and attempt < 2:
            continue
        break
    assert [p.returncode for p in procs] == [0, 0], [log[-3000:] for log in logs]
    single = subprocess.run(args + ["--out", str(tmp_path / "single")], cwd=ROOT, text=True, capture_output=True,
                            env=dict(env, XLA_FLAGS="--xla_force_host_platform_device_count=4"), timeout=600)
    assert single.returncode == 0, single.stderr[-3000:]
    for name in ("qtables.npz", "records.npz"):
        with np.load(out / name) as a, np.load(tmp_path / "single" / name) as b:
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files), name
    for name in ("episodes.csv", "episode_stats.csv", "eval.csv"):
        assert (out / name).read_bytes() == (tmp_path / "single" / name).read_bytes(), name
