"""``jaxrobo sweep`` and ``jaxrobo eval`` on 1, 3 and 4 forced CPU devices: the same bytes on every count.

Each count is a fresh process (XLA_FLAGS is read when JAX starts). The sweeps have 5 rows of 3 envs, so neither divides
the device counts: on 3 devices one padding row shares a device with a real row (as on 2), on 4 a whole device holds
padding only; their greedy evaluation runs inside the sharded program. ``jaxrobo eval`` flies a run's tables on shifted
physics on whatever devices there are. The cart-pole sweep runs on every count; the Goto-v2 sweep, whose step is the one
that rounded differently on several devices (see :data:`jaxrobo.speed.sharding.SPMD_DISABLED_PASSES`) and compiles for
~30 s, on 1 and 3. The runs are tiny (a few short episodes): the check is the bytes, not the learning.
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys

import pytest

from jaxrobo.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

TINY = ["--n-envs", "3", "--nepisodes", "3", "--set", "backend=analytic", "--set", "nsteps=30",
        "--set", "chunk_steps=30"]

CHILD = r"""
import sys
sys.path.insert(0, sys.argv[1])
import jax
from jaxrobo.cli import main
out, run = sys.argv[2], sys.argv[3]
tiny = sys.argv[4:]
assert main(["sweep", "--env", "CartPoleStayUp-v0", "--grid", "alpha=0.1,0.3,0.5,0.7,0.9", "--seeds", "1",
             "--eval-episodes", "2", "--no-plots", "--no-progress", "--out", out + "/sweep", *tiny]) == 0
assert main(["eval", run, "--shift", "pole_length=0.5,2", "--episodes", "3", "--tables", "3",
             "--out", out + "/robust"]) == 0
if jax.device_count() in (1, 3):
    assert main(["sweep", "--env", "QuadcopterGoto-v2", "--grid", "alpha=0.1,0.3,0.5,0.7,0.9", "--seeds", "1",
                 "--n-envs", "3", "--total-steps", "600", "--eval-episodes", "2", "--no-plots", "--no-progress",
                 "--out", out + "/goto"]) == 0
print("DEVICES", jax.device_count())
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("runs") / "cartpole")
    assert main(["train", "--env", "CartPoleStayUp-v0", "--out", out, "--no-progress", "--set", "eval_episodes=0",
                 *TINY]) == 0
    return out


def _digest(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@pytest.mark.slow
def test_sweep_and_eval_give_the_same_bytes_on_1_3_and_4_devices(run_dir, tmp_path):
    digests = {}
    for d in (1, 3, 4):
        out = tmp_path / f"d{d}"
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
               "XLA_FLAGS": f"--xla_force_host_platform_device_count={d}"}
        proc = subprocess.run([sys.executable, "-c", CHILD, ROOT, str(out), run_dir, *TINY], env=env,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert f"DEVICES {d}" in proc.stdout
        if d > 1:
            assert f"over {d} devices" in proc.stdout  # the sweep did split its rows
        digests[d] = (_digest(out / "sweep" / "sweep.csv"), _digest(out / "robust" / "robustness.csv"))
    assert len(set(digests.values())) == 1, digests
    assert _digest(tmp_path / "d1" / "goto" / "sweep.csv") == _digest(tmp_path / "d3" / "goto" / "sweep.csv")


RESUME_CHILD = r"""
import sys
sys.path.insert(0, sys.argv[1])
import jax
from jaxrobo.speed.sharding import make_mesh
from jaxrobo.training import sweep
state, step = sys.argv[2], sys.argv[3]
plan = sweep.plan_sweep("CartPoleStayUp-v0", [{"alpha": a} for a in (0.1, 0.3, 0.5, 0.7, 0.9)], seeds=[0],
                        agent="qlearn", overrides={"n_envs": 3, "nepisodes": 3, "nsteps": 30, "chunk_steps": 10,
                                                   "backend": "analytic"}, eval_episodes=2)
mesh = make_mesh() if jax.device_count() > 1 else None
chunks = []
if step == "stop":
    try:
        sweep.run_plan(plan, mesh, state_dir=state, progress=lambda p: chunks.append(p.chunks_done),
                       should_stop=lambda: len(chunks) == 2)
    except sweep.SweepInterrupted as err:
        assert err.partial[:2] == (0, 2), err.partial
    else:
        raise AssertionError("not stopped")
else:  # the uninterrupted sweep, then the stopped one resumed
    sweep.write_csv(sweep.run_plan(plan, mesh), sys.argv[4] + "/whole.csv")
    lines = []
    result = sweep.run_plan(plan, mesh, log=lines.append, state_dir=state)
    assert any("going on from chunk 2" in line for line in lines), lines
    sweep.write_csv(result, sys.argv[4] + "/resumed.csv")
print("DEVICES", jax.device_count())
"""


@pytest.mark.slow
def test_a_sweep_stopped_inside_a_group_resumes_on_another_device_count(tmp_path):
    """A sweep stopped inside a group on 4 devices (5 rows padded to 8) goes on from its saved chunk on 3 devices
    (padded to 6) and writes the uninterrupted sweep's sweep.csv byte for byte: the group's carry is saved with its
    rows only, where its padding rows, which follow the device count, refused it on any other count."""
    state = tmp_path / "state"
    state.mkdir()
    for d, step in ((4, "stop"), (3, "resume")):
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
               "XLA_FLAGS": f"--xla_force_host_platform_device_count={d}"}
        proc = subprocess.run([sys.executable, "-c", RESUME_CHILD, ROOT, str(state), step, str(tmp_path)], env=env,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert f"DEVICES {d}" in proc.stdout
    assert (tmp_path / "resumed.csv").read_bytes() == (tmp_path / "whole.csv").read_bytes()
