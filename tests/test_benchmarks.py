"""Smoke test of the main job, benchmarks/throughput.py, at tiny sizes (the figures themselves are benchmarks)."""
from __future__ import annotations

import csv
import importlib
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _script(name: str, folder: str = "benchmarks"):
    """A benchmark script imported as a module; its folder stays on ``sys.path`` for the imports it makes later."""
    path = os.path.join(ROOT, folder)
    if path not in sys.path:
        sys.path.insert(0, path)
    return importlib.import_module(name)


@pytest.mark.slow
def test_throughput_smoke(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": str(tmp_path / "cache"),
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "throughput.py"), "--n-envs", "4", "--steps", "10",
           "--repeats", "1", "--envs", "CartPoleStayUp-v0,NoSuchEnv-v0", "--backends", "mjx,analytic",
           "--learners", "qlearn", "--peers", "gymnasium,seed-loop,gymnax,l2f", "--out", str(tmp_path / "out"),
           "--commands", "train-steps", "--command-envs", "CartPoleStayUp-v0:analytic", "--command-n-envs", "4",
           "--steps-per-env", "30", "--time-to-trained", "none"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
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
    text = (tmp_path / "out" / "throughput.txt").read_text()  # the stdout table, as a plain file beside the JSON
    assert text.startswith("jaxrobo throughput on ") and "x phys" in text and "published, other machine" in text
    assert "x phys" in proc.stdout and rows[("l2f", "quadrotor", "env")]["status"] == "published"
    assert (tmp_path / "out" / "throughput_cartpole.png").stat().st_size > 0
    assert not (tmp_path / "out" / "throughput.partial.json").exists()  # the rows-so-far file, gone once complete
    assert not (tmp_path / "out" / "throughput_quadcopter.png").exists()  # L2F's figure has no batch size to plot
    backends = {r["backend"] for r in data["rows"] if r["suite"] == "jaxrobo" and r["status"] == "ok"}
    assert backends == {"mjx", "analytic"}
    # the user's own command as a row: jaxrobo train end to end under the step budget, every slot useful
    cli = rows[("jaxrobo-cli", "CartPoleStayUp-v0", "train-steps")]
    assert cli["status"] == "ok" and cli["env_steps"] == 4 * 30 and cli["useful_share"] == 1.0, cli
    assert cli["wall_s"] > cli["compile_s"] > 0 and "--total-steps 120" in cli["command"]


@pytest.mark.slow
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


def test_throughput_plan_matches_brax_physics_step_and_ratios_use_the_same_size():
    """The like-for-like rows: cart-pole on MJX at Brax inverted_pendulum's physics step, beside its rows."""
    throughput = _script("throughput")

    dt = throughput.brax_physics_dt()
    assert dt == 0.02, dt  # Brax's inverted_pendulum.xml; the cart-pole's default is 0.01
    args = throughput.parse_args(["--envs", "CartPoleStayUp-v0", "--backends", "mjx", "--learners", "qlearn",
                                  "--peers", "brax"])
    plan = throughput.jaxrobo_plan(args, (4, 64), gpu=False)
    assert ("run", "CartPoleStayUp-v0", "mjx", "qlearn", 64, {"timestep": dt}) in plan
    assert ("run", "CartPoleStayUp-v0", "mjx", None, 64, {"timestep": dt}) in plan
    assert not any(item[-1] for item in plan if item[0] == "run" and item[4] == 4)  # Brax runs at the largest only
    no_brax = throughput.jaxrobo_plan(throughput.parse_args(["--envs", "CartPoleStayUp-v0", "--peers", "gymnax"]),
                                      (4,), gpu=False)
    assert not any(item[-1] for item in no_brax if item[0] == "run")
    rows = [{"suite": "jaxrobo", "env": "CartPoleStayUp-v0", "status": "ok", "n_envs": n, "steps_per_s": 100.0 * n}
            for n in (4, 64)]
    rows.append({"suite": "brax", "env": "inverted_pendulum/mjx", "status": "ok", "n_envs": 64, "steps_per_s": 1600.0})
    throughput._ratios(rows)
    assert rows[1]["x_brax"] == 4.0 and "x_brax" not in rows[0]
    assert throughput._backend_label("mjx", {"timestep": dt}) == "mjx dt=0.02"


def test_time_carry_fills_short_samples_with_back_to_back_calls():
    import time

    _common = _script("_common")

    calls = []

    def fn(carry, _):
        calls.append(1)
        time.sleep(0.01)
        return carry + 1, None

    seconds, carry = _common.time_carry(fn, 0, 0, repeats=2, min_seconds=0.05)
    assert carry == len(calls) and len(calls) >= 1 + 2 * 4  # warm-up, then two samples of >= 4 calls each
    assert 0.009 < seconds < 0.05  # per call, not per sample
    calls.clear()
    _common.time_carry(fn, 0, 0, repeats=3)
    assert len(calls) == 4  # without min_seconds: one call per sample


def test_append_merges_parts_replacing_rows_measured_again(tmp_path):
    """``--append``: a long matrix runs in parts; a row measured again replaces the old one, ratios are
    recomputed over the merged rows, and another device's results are refused."""
    throughput = _script("throughput")

    def row(suite, mode, n, sps, **kw):
        return {"suite": suite, "env": "CartPoleStayUp-v0" if suite == "jaxrobo" else "inverted_pendulum/mjx",
                "backend": "mjx", "mode": mode, "n_envs": n, "status": "ok", "steps_per_s": sps, **kw}

    assert throughput.load_earlier(str(tmp_path), "cpu") == {"meta": None, "rows": []}
    first = {"meta": {"device": "cpu", "argv": ["part0"], "jax": "x"},
             "rows": [row("jaxrobo", "qlearn", 64, 10.0, x_brax=99.0), row("brax", "env", 64, 5.0)]}
    (tmp_path / "throughput.json").write_text(json.dumps(first))
    earlier = throughput.load_earlier(str(tmp_path), "cpu")
    rows, parts = throughput.merge_rows(earlier, [row("jaxrobo", "env", 64, 40.0), row("brax", "env", 64, 8.0)],
                                        {"argv": ["part1"], "jax": "x"})
    assert [p["argv"] for p in parts] == [["part0"], ["part1"]]
    assert [(r["mode"], r["steps_per_s"], r["part"]) for r in rows] == [
        ("qlearn", 10.0, 0), ("env", 40.0, 1), ("env", 8.0, 1)]  # the Brax row measured again replaced the old one
    throughput._ratios(rows)
    assert rows[0]["x_brax"] == 10.0 / 8.0 and rows[1]["x_brax"] == 5.0
    assert "2 runs merged with --append" in throughput.table(rows)
    with pytest.raises(SystemExit, match="holds results of 'cpu'"):
        throughput.load_earlier(str(tmp_path), "NVIDIA H100 80GB HBM3")


def test_env_groups_smoke_gives_the_same_tables_for_every_group_size(tmp_path):
    # XLA's default optimisation: at --xla_backend_optimization_level=0 the CPU code of the table update can round
    # its last bit differently when the env step around it is compiled differently.
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off"}
    out = tmp_path / "groups.json"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "studies", "env_groups.py"), "--backend", "analytic",
           "--n-envs", "7", "--groups", "all,3", "--steps", "20", "--repeats", "1", "--out", str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert [r["env_group"] for r in rows] == ["all", "3"] and all(r["steps_per_s"] > 0 for r in rows)
    assert rows[0]["q_fingerprint_after_one_chunk"] == rows[1]["q_fingerprint_after_one_chunk"]


@pytest.mark.slow
def test_time_to_trained_times_brax_s_own_pendulum_as_a_peer(tmp_path):
    """``time_to_trained.py --peers``: Brax's PPO on its inverted_pendulum in a fresh process, timed start to exit,
    each evaluation's return and time kept (here its settings shrunk to a smoke run, and said so in the row)."""
    shrunk = ["num_envs=8", "batch_size=8", "num_minibatches=1", "episode_length=20", "num_evals=2",
              "num_timesteps=40"]
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "time_to_trained.py"), "--envs", "--peers",
           "--warm-only", "--out", str(tmp_path), *[f"--peer-set={s}" for s in shrunk]]
    proc = subprocess.run(cmd, env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (row,) = json.loads((tmp_path / "time_to_trained.json").read_text())["rows"]
    assert row["env_id"] == "brax:inverted_pendulum" and row["exit_code"] == 0 and row["cache"] == "warm"
    assert row["agent"] == "ppo (Brax's notebook settings; changed: " + ", ".join(shrunk) + ")"
    assert row["env_steps"] == 40 and row["settings"]["num_envs"] == 8 and row["backend"] == "positional"
    steps = [e[0] for e in row["evals"]]
    assert steps == sorted(steps) and steps[-1] == 40 and all(0 < e[2] < row["wall_seconds"] for e in row["evals"])
    assert row["learning_value"] == row["evals"][-1][1] and row["learning_target"] == "evaluation return >= 500"
    assert (row["target_met_at_seconds"] is None) == all(e[1] < 500 for e in row["evals"])
    bad = subprocess.run(cmd[:2] + ["--peers", "--peer-set", "gamma=3"], capture_output=True, text=True,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=120)
    assert bad.returncode == 2 and "--peer-set gamma=3" in bad.stderr


@pytest.mark.slow
def test_chunk_collectives_finds_the_exchanges_in_the_step_loop(tmp_path):
    """benchmarks/studies/chunk_collectives.py over 4 forced CPU devices: every task's partitioned chunk has a step
    loop that exchanges data (the figures docs/scaling.md cites), and a device count it cannot see is refused."""
    script = os.path.join(ROOT, "benchmarks", "studies", "chunk_collectives.py")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    out = tmp_path / "collectives.json"
    proc = subprocess.run([sys.executable, script, "--out", str(out)], env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    chunks = json.loads(out.read_text())["chunks"]
    assert [c["env"] for c in chunks] == ["CartPoleStayUp-v0", "QuadcopterGoto-v2", "ArmReach-v0"]
    for c in chunks:
        assert "devices=4" in c["plan"] and not c["one_program_per_device"], c
        assert any(loop["collectives_per_iteration"].get("all-gather", 0) > 0 for loop in c["loops"]), c
    assert [c["shared_table"] for c in chunks] == [False, True, True]
    refused = subprocess.run([sys.executable, script, "--devices", "8"], env=env, capture_output=True, text=True,
                             timeout=300)
    assert refused.returncode == 1 and "sees 4 device(s)" in refused.stderr


def test_fused_plan_tokens_name_the_kernel_choices():
    """benchmarks/studies/fused.py's plan tokens: each turns one of the chunk kernel's plan choices off, printed in
    the plan's tag, and they apply to pallas only."""
    fused = _script("fused", os.path.join("benchmarks", "studies"))

    from jaxrobo.speed.plan import ExecutionPlan

    plan = fused.plan_of(ExecutionPlan(), "pallas:64:always:lanes:libdevice")
    assert (plan.fused, plan.fused_block) == ("pallas", 64)
    assert (plan.skip_resets, plan.group_resets, plan.fast_sincos) == (False, False, False)
    assert repr(plan).endswith("fused=pallas, fused_block=64, skip_resets=off, group_resets=off, fast_sincos=off)")
    assert fused.plan_of(ExecutionPlan(), "pallas:lanes") == ExecutionPlan(fused="pallas", group_resets=False)
    with pytest.raises(ValueError, match="apply to pallas only"):
        fused.plan_of(ExecutionPlan(), "xla:lanes")


def test_randomisation_cost_refuses_an_unknown_variant_before_anything_runs():
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "randomisation_cost.py"),
                           "--variants", "kernel-nominal,kernel-randomized"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert "--variants kernel-randomized: expected a comma list of kernel-nominal" in proc.stderr


def test_randomisation_cost_configures_every_case_and_variant():
    """Every env id and variant the benchmark times resolves to a valid run (a preset's later default, such as the
    Goto presets' snapshots, must not stop its GPU rows after minutes of compiling the others)."""
    randomisation_cost = _script("randomisation_cost")
    from jaxrobo.training.run import resolve

    for env_id in randomisation_cost.CASES:
        for variant in randomisation_cost.VARIANTS:
            spec = resolve(env_id, "default", {**randomisation_cost.overrides_for(env_id, variant), "n_envs": 8,
                                               "nepisodes": 2, "eval_episodes": 0})
            assert spec.env.randomised == (variant != "kernel-nominal"), (env_id, variant)


def test_kernel_occupancy_reads_ncu_details_and_refuses_without_ncu():
    kernel_occupancy = _script("kernel_occupancy")
    recorded = os.path.join(ROOT, "tests", "data", "ncu_kernel-nominal.txt")  # Nsight Compute's output on an H100
    with open(recorded) as f:
        row = kernel_occupancy.parse(f.read())
    assert row == {"registers": 96.0, "blocks_per_sm_by_registers": 20.0, "theoretical_occupancy_percent": 31.25,
                   "achieved_occupancy_percent": 27.82, "issued_ipc": 2.71, "duration": 13.8, "duration_unit": "ms"}
    if kernel_occupancy.find_ncu() is None:  # CI: no Nsight Compute; the script says so before anything runs
        proc = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "kernel_occupancy.py")],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and "no ncu found" in proc.stderr


@pytest.mark.slow
def test_time_to_trained_times_the_users_command_and_splits_its_wall(tmp_path):
    """benchmarks/time_to_trained.py: one warm row of a tiny arm run, its wall split by the run's own summary."""
    ttt = _script("time_to_trained")
    rows = ttt.collect([("ArmReach-v0", None)], seeds=1, cold=False,
                       sets=["nepisodes=3", "eval_episodes=4", "n_envs=4", "nsteps=20"])
    (row,) = rows
    assert row["exit_code"] == 0 and row["cache"] == "warm" and 0 < row["env_steps"] <= 4 * 3 * 20
    parts = [row[k] for k in ("startup_seconds", "compile_seconds", "run_seconds", "evaluation_seconds",
                              "writing_seconds")]
    assert all(v is not None and v >= 0 for v in parts) and sum(parts) <= row["wall_seconds"]
    assert row["learning_figure"] == "eval_best_table_success_rate" and 0 <= row["learning_value"] <= 1
    assert "ArmReach-v0 | preset | warm" in ttt.table(rows)


def test_startup_reaches_the_first_chunk_through_trains_callbacks(tmp_path):
    """benchmarks/startup.py's child stops at the first chunk from a progress function; it once passed it as
    ``train(progress=...)``, a keyword train() no longer takes (a TypeError before anything ran)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "startup.py"), "--runs", "1", "--n-envs", "2",
           "--chunk-steps", "10", "--set", "backend=analytic", "--cache-dir", str(tmp_path / "cache"),
           "--out", str(tmp_path / "startup.json")]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = json.loads((tmp_path / "startup.json").read_text())["runs"][0]
    assert run["to_first_chunk_s"] > 0 and run["cache_entries_after"] > 0


@pytest.mark.slow
def test_learners_compare_runs_the_pages_commands_and_keeps_each_runs_figures(tmp_path):
    """benchmarks/learners_compare.py shrunk: docs/cartpole.md's commands (2 envs, 20 episodes, 5 greedy
    episodes a table), one row each with every figure of the page's table, consistent with the runs' own files,
    and the page's plot command's picture."""
    lc = _script("learners_compare")
    out, png, work = tmp_path / "lc.json", tmp_path / "compare.png", tmp_path / "work"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "learners_compare.py"), "--n-envs", "2", "--nepisodes",
           "20", "--eval-episodes", "5", "--png", str(png), "--work", str(work), "--out", str(out)]
    proc = subprocess.run(cmd, env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads(out.read_text())
    assert data["device"].startswith("cpu (") and data["code"] and data["command"].endswith(" ".join(cmd[2:]))
    assert data["n_envs"] == 2 and png.stat().st_size > 0 and "jaxrobo plot runs/cpu_cartpole_qlearn" in data["note"]
    rows = data["rows"]
    assert [r["run"] for r in rows] == ["cpu_cartpole_qlearn", "cpu_cartpole_sarsa", "cpu_cartpole_seed",
                                        "cpu_cartpole_expected_sarsa", "cpu_cartpole_double_q",
                                        "cpu_cartpole_double_q_shared"]
    assert [r["agent"] for r in rows] == ["qlearn", "sarsa", "qlearn", "expected_sarsa", "double_q", "double_q"]
    assert [r["shared_table"] for r in rows] == [False] * 5 + [True]
    assert "double_q" not in data["note"].split("; then ")[1]  # the picture draws the page's three runs
    assert [r["command"] for r in rows] == [" ".join(["jaxrobo", *c]) for c in lc.commands(2, 20, 5)]
    assert "--preset seed" in rows[2]["command"] and "stop_at_target=false" not in rows[2]["command"]
    for r in rows:
        assert r["exit_code"] == 0 and r["n_envs"] == 2 and r["nepisodes"] == 20 and r["seed"] == 0, r
        tables = 1 if r["shared_table"] else 2
        assert r["tables_evaluated"] == tables and 0 <= r["tables_ge_500"] <= tables, r
        assert r["eval_episodes_per_table"] == r["fresh_episodes"] == 5, r
        fresh = [] if r["shared_table"] else ["selected_table_fresh_mean_length"]  # one table: none selected
        for key in ("best_100_window_mean_length", "eval_mean_length", "last_100_mean_length", *fresh):
            assert 1 <= r[key] <= 1000, (key, r)
        if r["shared_table"]:
            assert r["selected_table_fresh_mean_length"] is None, r
        assert r["eval_mean_length"] <= r["eval_best_table_mean_length"] + 1e-6, r
        rise = [r[f"first_episode_window_ge_{level}"] for level in lc.RISE]
        assert rise[0] is not None or rise[1] is None, r
        assert all(0 <= e < 20 for e in rise if e is not None) and (None in rise or rise[0] <= rise[1]), r
        if not r["stop_at_target"]:
            assert r["episodes_finished"] == 2 * 20, r
        again = lc.figures(str(work / "runs" / r["run"]))  # the row is what the run directory holds
        assert {k: r[k] for k in again} == again
    bad = subprocess.run(cmd[:2] + ["--n-envs", "0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--n-envs 0: expected an integer >= 1" in bad.stderr


@pytest.mark.slow
def test_ros_sim2sim_keeps_every_rows_figures(tmp_path):
    """benchmarks/ros_sim2sim.py shrunk (the Goto-v2 run, 2 episodes a row, ROS left out): the train row, both pages'
    sim2sim rows with each side's outcomes, and the ROS rows kept as skipped with the reason."""
    out = tmp_path / "ros_sim2sim.json"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "ros_sim2sim.py"), "--runs", "goto2", "--episodes", "2",
           "--no-ros", "--out", str(out)]
    proc = subprocess.run(cmd, env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    data = json.loads(out.read_text())
    assert data["device"] and data["code"] and data["command"] and "Shrunk" in data["note"]
    kinds = [(r["kind"], r.get("page") or r.get("name")) for r in data["rows"]]
    assert kinds == [("train", None), ("sim2sim", "real_robot"), ("sim2sim", "ros"), ("ros", "goto2_lockstep"),
                     ("ros", "goto2_speed10")], kinds
    train = data["rows"][0]
    assert train["exit_code"] == 0 and train["export_exit_code"] == 0 and 0 <= train["eval_success_rate"] <= 1
    for r in data["rows"][1:3]:
        assert r["status"] == "ok" and r["episodes"] == 2 and r["env_id"] == "QuadcopterGoto-v2", r
        assert 0 <= r["identical_flights"] <= r["same_outcome"] <= r["episodes"]
        for side in ("native", "jax_export", "jax_evaluation"):
            assert 0 <= r[f"{side}_success_rate"] <= 1 and r[f"{side}_successes"] <= r["episodes"]
        agree, total = r["runner_on_jax_obs"]
        assert agree == total == r["steps_jax_export"] > 0
        assert len(r["parted_at"]) == r["episodes"] - r["identical_flights"]
        assert all(len(v) == r["episodes"] for side in r["sides"].values() for v in side.values())
        assert r["native_successes"] == sum(r["sides"]["native"]["success"])
    assert [r["seed"] for r in data["rows"][1:3]] == [12345, 12345]
    for r in data["rows"][3:]:
        assert r["status"] == "skipped" and "--no-ros" in r["reason"] and r["episodes"] <= 2
