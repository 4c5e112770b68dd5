"""``jaxrobo train`` over several devices (``ExecutionPlan.devices``): on 4 forced host devices the tables, records,
counters and evaluation are those of one device, bit for bit, per-env tables and a shared table alike, under every
budget, the analytic cart-pole and the quadcopter; the greedy flights fly on the first device;
the CLI splits its envs over every device by default and writes one run directory.

XLA_FLAGS must be set before JAX starts, so the check runs in a subprocess, at XLA's default optimisation level
(the level users run; a shared table's sums are compared bit for bit, and XLA may order a scatter-add otherwise in
a program compiled at another level)."""
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
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train

small = dict(n_envs=8, nepisodes=4, nsteps=40, chunk_steps=25, eval_episodes=2, eval_envs=2, backend="analytic")
out = {"devices": jax.device_count(), "cases": {}}
# 16 envs over 4 devices: XLA's CPU code rounds the quadcopter's step by its batch, and other splits (8 or 64
# envs over 4) move its last bits (docs/scaling.md)
goto = dict(n_envs=16, nepisodes=4, nsteps=40, chunk_steps=25, eval_episodes=2, eval_envs=2)
cases = {"per_env": {}, "shared": {"shared_table": True}, "steps": {"total_steps": 8 * 60},
         "pallas": {"fused": "pallas"},
         # 8 snapshots of the shared table: as many as the envs, yet not split over the devices
         "snapshots": {"shared_table": True, "snapshots": 8, "snapshot_episodes": 2},
         # a physics step with reductions (XLA's CPU partitioner otherwise rounds them otherwise than one device)
         "goto_per_env": ("QuadcopterGoto-v2", {**goto, "shared_table": False, "snapshots": 0}),
         "goto_shared": ("QuadcopterGoto-v2", {**goto, "shared_table": True}),
         # a step budget that 8 envs do not divide: each device's share steps ceil(total / 8) steps an env
         "one_program_steps": {"total_steps": 8 * 60 + 5}, "one_program_episodes": {}}
from jaxrobo.training import driver
partitioned, taken = driver.per_device_chunk, []
# Where the flights fly: a split run's on its first device, with the one-device programs
flown, fly = set(), driver.Flights.fly
driver.Flights.fly = lambda self, *a, **k: flown.add((self.trainer.plan.devices, str(self.device))) \
    or fly(self, *a, **k)
for name, extra in cases.items():
    env_id, extra = extra if isinstance(extra, tuple) else ("CartPoleStayUp-v0", {**small, **extra})
    # "one_program_*": each device's envs stepped by the one-device program (shard_map), the split GPUs take for
    # independent envs, taken on these CPUs for the cart-pole (whose CPU rounding does not follow the batch)
    driver.per_device_chunk = (lambda trainer, mesh: not taken.append(name)) if name.startswith("one_program") \
        else partitioned
    res = {}
    for d in (1, 4):
        spec = resolve(env_id, overrides={**extra, "devices": d})
        res[d] = train(spec.env, spec.config, spec.agent_params)
    out["cases"][name] = {
        "plan": res[4].plan, "env_steps": int(res[4].env_steps),
        "same": {k: bool(np.array_equal(np.asarray(getattr(res[1], k)), np.asarray(getattr(res[4], k))))
                 for k in ("q", "returns", "lengths", "terminated", "env_steps", "eval_returns", "eval_success",
                           "final_table_choice")},
        "selected": json.dumps(res[1].selected, default=str) == json.dumps(res[4].selected, default=str)}
out["one_program_taken"] = sorted(set(taken))
out["flown"], out["first_device"] = sorted(flown), str(jax.devices()[0])
from jaxrobo.cli import main
rc = main(["train", "--env", "CartPoleStayUp-v0", "--set", "env.backend=analytic", "--n-envs", "6",
           "--total-steps", "300", "--set", "chunk_steps=25", "--set", "nsteps=40", "--set", "eval_episodes=2",
           "--no-progress", "--out", sys.argv[2]])
out["cli_rc"] = rc
print("RESULT" + json.dumps(out))
"""


@pytest.mark.slow
def test_several_devices_give_the_one_device_tables(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-c", CHILD, ROOT, str(run)], env=env, capture_output=True, text=True,
                          timeout=1500)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("RESULT", 1)[1])
    assert out["devices"] == 4
    for name, case in out["cases"].items():
        assert "devices=4" in case["plan"], (name, case["plan"])
        assert all(case["same"].values()) and case["selected"], (name, case["same"])
    assert "fused=pallas" in out["cases"]["pallas"]["plan"]
    assert out["cases"]["one_program_steps"]["env_steps"] == 8 * 61
    assert out["one_program_taken"] == ["one_program_episodes", "one_program_steps"]
    assert out["flown"] == [[1, "None"], [4, out["first_device"]]]  # the split runs' flights: on one device
    # the CLI: 6 envs over the most of the 4 devices that divide 6 (3), one run directory
    assert out["cli_rc"] == 0
    summary = json.loads((run / "summary.json").read_text())
    assert "devices=3" in summary["execution_plan"] and summary["env_steps"] == 300
    assert not list(tmp_path.glob(".run.*"))  # no staging left beside it


RESUME_CHILD = r"""
import signal, sys
sys.path[:0] = [sys.argv[1], sys.argv[1] + "/tests"]
from jaxrobo.cli import main
from jaxrobo.training import checkpoint
from stop_at_save import after_chunk, signal_after_save

out = sys.argv[2]
tiny = ["--env", "CartPoleStayUp-v0", "--n-envs", "8", "--nepisodes", "6", "--set", "nsteps=20",
        "--set", "chunk_steps=10", "--set", "backend=analytic", "--set", "eval_episodes=1", "--set", "devices=4",
        "--set", "stop_at_target=false", "--no-progress"]
with signal_after_save(checkpoint, signal.SIGTERM, after_chunk(1)):
    assert main(["train", *tiny, "--checkpoint-every", "1", "--out", out + "/stopped"]) == 143
assert main(["train", "--resume", out + "/stopped", "--no-progress"]) == 0
assert main(["train", *tiny, "--out", out + "/whole"]) == 0
"""


def test_a_run_split_over_devices_resumes_to_the_uninterrupted_runs_files(tmp_path):
    """A run over 4 devices stopped after its first checkpoint resumes (its carry placed over the devices as a fresh
    one is: the programs compiled from it take every later carry) to the uninterrupted run's files, bit for bit."""
    import numpy as np

    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    proc = subprocess.run([sys.executable, "-c", RESUME_CHILD, ROOT, str(tmp_path)], env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("qtables.npz", "records.npz"):
        with np.load(tmp_path / "stopped" / name) as a, np.load(tmp_path / "whole" / name) as b:
            assert sorted(a.files) == sorted(b.files) and all(np.array_equal(a[k], b[k]) for k in a.files), name
    for name in ("episodes.csv", "episode_stats.csv", "eval.csv"):
        assert (tmp_path / "stopped" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name


FEWER_CHILD = r"""
import signal, sys
sys.path[:0] = [sys.argv[1], sys.argv[1] + "/tests"]
from jaxrobo.cli import main
from jaxrobo.training import checkpoint
from stop_at_save import after_chunk, signal_after_save

out, step = sys.argv[2], sys.argv[3]
tiny = ["--env", "CartPoleStayUp-v0", "--n-envs", "8", "--nepisodes", "6", "--set", "nsteps=20",
        "--set", "chunk_steps=10", "--set", "backend=analytic", "--set", "eval_episodes=1",
        "--set", "stop_at_target=false", "--no-progress"]
if step == "stop":  # split over the 4 devices by --devices, stopped after its first checkpoint
    with signal_after_save(checkpoint, signal.SIGTERM, after_chunk(1)):
        assert main(["train", *tiny, "--devices", "4", "--checkpoint-every", "1", "--out", out + "/stopped"]) == 143
else:  # on 2 devices
    assert main(["train", "--resume", out + "/stopped", "--no-progress"]) == 2
    assert main(["train", "--resume", out + "/stopped", "--devices", "-1", "--no-progress"]) == 2
    assert main(["train", "--resume", out + "/stopped", "--devices", "2", "--no-progress"]) == 0
    assert main(["train", *tiny, "--devices", "2", "--out", out + "/whole"]) == 0
"""


def test_a_run_split_over_4_devices_resumes_on_2_with_devices(tmp_path):
    """A run split over 4 devices by --devices 4 and stopped goes on on a host of 2 with --resume DIR --devices 2,
    to the uninterrupted run's files bit for bit, where --devices was refused with --resume and the run's own
    devices=4 could then not go on anywhere with fewer devices. Without --devices it is refused in one line that
    names the flag; the run's config.yaml keeps its own devices."""
    import numpy as np

    procs = {}
    for step, d in (("stop", 4), ("resume", 2)):
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
               "XLA_FLAGS": f"--xla_force_host_platform_device_count={d}"}
        procs[step] = subprocess.run([sys.executable, "-c", FEWER_CHILD, ROOT, str(tmp_path), step], env=env,
                                     capture_output=True, text=True, timeout=900)
        assert procs[step].returncode == 0, procs[step].stderr[-3000:]
    err = procs["resume"].stderr
    assert "split over devices=4 and there are only 2 here; --devices N goes on" in err, err[-3000:]
    assert "--devices=-1: expected an integer >= 0" in err, err[-3000:]
    assert "devices=2)" in procs["resume"].stdout  # the resumed run's plan line
    for name in ("qtables.npz", "records.npz"):
        with np.load(tmp_path / "stopped" / name) as a, np.load(tmp_path / "whole" / name) as b:
            assert sorted(a.files) == sorted(b.files) and all(np.array_equal(a[k], b[k]) for k in a.files), name
    for name in ("episodes.csv", "episode_stats.csv", "eval.csv"):
        assert (tmp_path / "stopped" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
    assert "devices: 4" in (tmp_path / "stopped" / "config.yaml").read_text()
