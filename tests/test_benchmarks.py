"""Smoke test of the main job, benchmarks/throughput.py, at tiny sizes (the figures themselves are benchmarks)."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_throughput_smoke(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": str(tmp_path / "cache"),
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "throughput.py"), "--n-envs", "4", "--steps", "10",
           "--repeats", "1", "--envs", "CartPoleStayUp-v0,NoSuchEnv-v0", "--backends", "mjx,analytic",
           "--learners", "qlearn", "--peers", "gymnasium,seed-loop,gymnax", "--out", str(tmp_path / "out")]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads((tmp_path / "out" / "throughput.json").read_text())
    rows = {(r["suite"], r["env"], r["mode"]): r for r in data["rows"]}
    for key in (("jaxrobo", "CartPoleStayUp-v0", "env"), ("jaxrobo", "CartPoleStayUp-v0", "qlearn"),
                ("gymnasium", "CartPole-v1", "env"), ("seed-loop", "CartPole-v1", "qlearn")):
        assert rows[key]["status"] == "ok" and rows[key]["steps_per_s"] > 0, rows[key]
    q = rows[("jaxrobo", "CartPoleStayUp-v0", "qlearn")]
    assert q["qtable_bytes"] == q["n_states"] * 4 * 4 and q["x_seed_loop"] > 0 and q["compile_s"] > 0
    assert q["physics_steps_per_s"] == q["steps_per_s"] * q["n_substeps"]
    gymnax = rows[("gymnax", "CartPole-v1", "env")]
    assert gymnax["status"] in ("ok", "skipped")  # skipped, with a reason, when the bench extra is absent
    assert rows[("jaxrobo", "NoSuchEnv-v0", "-")]["status"] == "skipped"
    assert all(r.get("reason") for r in data["rows"] if r["status"] != "ok")
    with open(tmp_path / "out" / "throughput.csv") as f:
        assert len(list(csv.DictReader(f))) == len(data["rows"])
    assert (tmp_path / "out" / "throughput.png").stat().st_size > 0
    assert "x best peer" in proc.stdout
    backends = {r["backend"] for r in data["rows"] if r["suite"] == "jaxrobo" and r["status"] == "ok"}
    assert backends == {"mjx", "analytic"}


def test_time_to_learn_smoke_covers_the_cartpole_and_the_goto_task(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": str(tmp_path / "cache"),
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    out = tmp_path / "ttl.json"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "time_to_learn.py"), "--backend", "analytic",
           "--n-envs", "8", "--chunk-steps", "100", "--eval-every", "1", "--eval-tables", "2", "--budget", "0.5",
           "--skip-seed-loop", "--goto-runs", "2", "--out", str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = {r["env"]: r for r in json.loads(out.read_text())["rows"]}
    cart, goto = rows["CartPoleStayUp-v0"], rows["QuadcopterGoto-v1"]
    assert cart["evaluations"] and 1 <= cart["best_mean_length"] <= 1000
    assert goto["runs"] == 2 and goto["evaluations"] and 0.0 <= goto["best_success"] <= 1.0
    assert 0.0 <= goto["selected_fresh_success"] <= 1.0 and goto["met"] == (goto["best_success"] >= 0.8)
