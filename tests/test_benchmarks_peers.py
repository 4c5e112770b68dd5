"""The throughput benchmark's peers, like-for-like ratios and figures, on small fake results (no timing)."""
from __future__ import annotations

import json
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import figures  # noqa: E402
import throughput  # noqa: E402


def _row(suite, env, n, sps, sub=1, control_dt=0.02, mode="env", backend="-", status="ok", **kw):
    return {"suite": suite, "env": env, "backend": backend, "mode": mode, "n_envs": n, "status": status,
            "steps_per_s": sps, "n_substeps": sub, "control_dt": control_dt, "physics_dt": control_dt / sub,
            "physics_steps_per_s": sps * sub, "sim_seconds_per_s": sps * control_dt, **kw}


def fake_rows() -> list[dict]:
    """Two sizes of cart-pole (mjx 4 substeps at 0.04 s, analytic) and one of the quadcopter, with peers."""
    rows = []
    for n in (64, 1024):
        rows.append(_row("jaxrobo", "CartPoleStayUp-v0", n, 100.0 * n, sub=4, control_dt=0.04, backend="mjx"))
        rows.append(_row("jaxrobo", "CartPoleStayUp-v0", n, 50.0 * n, sub=4, control_dt=0.04, backend="mjx",
                         mode="qlearn"))
        rows.append(_row("jaxrobo", "CartPoleStayUp-v0", n, 400.0 * n, sub=4, control_dt=0.04,
                         backend="analytic", mode="qlearn"))
        rows.append(_row("gymnax", "CartPole-v1", n, 200.0 * n))
        rows.append(_row("playground", "CartpoleBalance", n, 20.0 * n, control_dt=0.01, backend="mjx-jax"))
    rows.append(_row("brax", "inverted_pendulum/mjx", 1024, 10.0 * 1024, sub=2, control_dt=0.04))
    rows.append(_row("jaxrobo", "QuadcopterGoto-v1", 1024, 1e5, sub=30, control_dt=0.03, mode="qlearn"))
    rows.append(_row("crazyflow", "quadrotor cf21B_500", 1024, 2e4, sub=5, control_dt=0.01,
                     backend="first-principles"))
    rows.append(_row("seed-loop", "CartPole-v1", 1, 1000.0, mode="qlearn", backend="numpy"))
    rows.append(throughput._skip("gymnasium", "CartPole-v1", "numpy", "env", 1, "not installed (x)"))
    rows.extend(throughput.published_rows(("crazyflow", "l2f")))
    rows.append(_row("jaxrobo", "ArmReach-v0", 1024, 1e6))  # an id of no family: no peer ratio
    return rows


def test_ratios_compare_like_for_like_per_env_step_physics_step_and_simulated_second():
    rows = fake_rows()
    throughput._ratios(rows)
    by = {(r["suite"], r["env"], r["backend"], r["mode"], r["n_envs"]): r for r in rows}
    mjx = by[("jaxrobo", "CartPoleStayUp-v0", "mjx", "env", 1024)]
    # the fastest cart-pole peer at 1024 by every measure is gymnax (200 n steps/s, 1 substep, 0.02 s)
    assert mjx["x_env"] == pytest.approx(100 / 200)
    assert mjx["x_phys"] == pytest.approx(100 * 4 / 200)
    assert mjx["x_sim"] == pytest.approx(100 * 0.04 / (200 * 0.02))
    assert mjx["peer"] == "gymnax n=1024"
    assert mjx["x_brax"] == pytest.approx(100 / 10) and mjx["x_seed_loop"] == pytest.approx(100 * 1024 / 1000)
    small = by[("jaxrobo", "CartPoleStayUp-v0", "mjx", "env", 64)]
    assert "x_brax" not in small and small["x_env"] == pytest.approx(0.5)  # Brax ran at 1024 only
    quad = by[("jaxrobo", "QuadcopterGoto-v1", "-", "qlearn", 1024)]
    # the quadcopter against crazyflow (measured), never against a cart-pole peer or a published figure
    assert quad["peer"] == "crazyflow n=1024" and quad["x_phys"] == pytest.approx(1e5 * 30 / (2e4 * 5))
    assert quad["x_sim"] == pytest.approx(1e5 * 0.03 / (2e4 * 0.01)) and "x_seed_loop" not in quad
    arm = by[("jaxrobo", "ArmReach-v0", "-", "env", 1024)]
    assert not any(k in arm for k in throughput.RATIO_KEYS)
    assert not any(k in r for r in rows if r["suite"] != "jaxrobo" for k in throughput.RATIO_KEYS)
    text = throughput.table(rows)
    for col in ("x env", "x phys", "x sim", "x brax", "x seed", " dt ", "sub"):
        assert col in text.splitlines()[0], col
    assert "per env step, per physics step and per simulated second" in text
    assert "published, other machine (RTX 4090): crazyflow" in text and "not installed (x)" in text


def test_published_figures_are_marked_other_machine_and_the_table_is_written_as_text(tmp_path):
    """A CPU figure beside a peer's published RTX 4090 figure: that bar is hatched, labelled "published, other
    machine" and explained in the panel's legend; its scaling curve is hollow and labelled the same; the table
    goes to a plain throughput.txt headed by the device and the command."""
    from matplotlib.patches import Rectangle

    rows = fake_rows()
    throughput._ratios(rows)
    fig = figures.headline_figure(rows, "cpu")
    quad = next(ax for ax in fig.axes if ax.get_title(loc="left").startswith("quadcopter"))
    labels = [t.get_text() for t in quad.get_yticklabels()]
    marked = [i for i, text in enumerate(labels) if "(published, other machine: " in text]
    assert len(marked) == 2 and any("RTX 4090" in labels[i] for i in marked)  # crazyflow's and L2F's figures
    bars = [p for p in quad.patches if isinstance(p, Rectangle) and p.get_width() > 0]
    assert sorted(i for i, b in enumerate(bars) if b.get_hatch()) == marked
    legend = [t.get_text() for t in quad.get_legend().get_texts()]
    assert legend == ["measured on cpu", figures.PUBLISHED_NOTE] and "other machine" in legend[1]
    cart = next(ax for ax in fig.axes if ax.get_title(loc="left").startswith("cart-pole"))
    assert cart.get_legend() is None  # no published bar there: nothing to explain
    series = figures.scaling_series(rows, "quadcopter")
    assert [k for k in series if "published" in k] == ["crazyflow: quadrotor cf21B_500 [first-principles] "
                                                       "(published, other machine: RTX 4090)"]
    path = tmp_path / "throughput.txt"
    throughput.write_table(rows, {"device": "cpu", "backend": "cpu", "cpu_count": 2,
                                  "argv": ["throughput.py", "--quick"]}, str(path))
    text = path.read_text()
    assert text.startswith("jaxrobo throughput on cpu (cpu, 2 CPU cores)\ncommand: throughput.py --quick\n\n")
    assert throughput.table(rows) in text and "published, other machine (RTX 4090)" in text


def test_published_rows_and_missing_peers_are_rows_with_their_reason():
    pub = {r["suite"]: r for r in throughput.published_rows(("crazyflow", "l2f"))}
    assert pub["crazyflow"]["status"] == "published" and pub["crazyflow"]["n_envs"] == 262144
    assert pub["crazyflow"]["physics_steps_per_s"] == 914e6 and "RTX 4090" in pub["crazyflow"]["reason"]
    assert pub["l2f"]["physics_steps_per_s"] == 20e9 and pub["l2f"]["sim_seconds_per_s"] is None
    assert throughput.published_rows(("gymnax",)) == []

    def missing(*_):
        raise ModuleNotFoundError("No module named 'crazyflow'", name="crazyflow")

    skip = throughput._skip("crazyflow", "quadrotor cf21B_500", "first-principles", "env", 8, "")
    row = throughput._guard(missing, skip)
    assert row["status"] == "skipped" and row["reason"] == ("not installed (crazyflow); "
                                                            "pip install 'jaxrobo[bench-quad]'")
    skip = throughput._skip("playground", "CartpoleBalance", "mjx-jax", "env", 8, "")
    assert "jaxrobo[bench]'" in throughput._guard(missing, skip)["reason"]

    def broken(*_):
        raise RuntimeError("two\nlines")

    assert throughput._guard(broken, skip)["reason"] == "RuntimeError: two lines"


def test_peer_plan_sizes_and_names_are_checked_up_front():
    args = throughput.parse_args(["--peers", "playground,crazyflow,l2f"])
    plan = {p: throughput.peer_plan(p, args, (64, 1024), gpu=False) for p in args.peers}
    assert [item[2] for item in plan["playground"]] == [1024]  # MJX peers: the largest size on a CPU
    assert [(item[0] is None, item[2]) for item in plan["crazyflow"]] == [(False, 1024), (True, 262144)]
    assert plan["l2f"][0][0] is None and plan["l2f"][0][1]["status"] == "published"
    gpu = throughput.peer_plan("crazyflow", args, (64, 1024), gpu=True)
    assert [item[2] for item in gpu if item[0] is not None] == [64, 1024]
    assert throughput.parse_args(["--peers", "none"]).peers == []
    with pytest.raises(SystemExit):
        throughput.parse_args(["--peers", "gymnax,nope"])


def test_figures_are_a_function_of_the_results_json(tmp_path, capsys):
    rows = fake_rows()
    cart = figures.headline_bars(rows, "cart-pole")
    labels = [b["label"] for b in cart]
    # jaxrobo with learning at its largest batch (one bar per env and backend), then each peer at its largest
    assert labels[:2] == ["jaxrobo: CartPoleStayUp-v0 [mjx] + qlearn", "jaxrobo: CartPoleStayUp-v0 [analytic] + qlearn"]
    assert all(b["n_envs"] == 1024 for b in cart[:2])
    assert {"gymnax: CartPole-v1", "playground: CartpoleBalance [mjx-jax]", "brax: inverted_pendulum/mjx",
            "seed-loop: CartPole-v1 + qlearn"} <= set(labels)
    assert not any("ArmReach" in x for x in labels)
    quad = figures.headline_bars(rows, "quadcopter")
    assert [b["published"] for b in quad] == [False, False, True, True]
    assert quad[0]["value"] == 1e5 * 30  # physics steps per second for the quadcopter family

    series = figures.scaling_series(rows, "cart-pole")
    assert series["jaxrobo: CartPoleStayUp-v0 [mjx] env"] == [(64, 6400.0), (1024, 102400.0)]
    assert set(series) == {"jaxrobo: CartPoleStayUp-v0 [mjx] env", "jaxrobo: CartPoleStayUp-v0 [mjx] qlearn",
                           "jaxrobo: CartPoleStayUp-v0 [analytic] qlearn", "gymnax: CartPole-v1",
                           "playground: CartpoleBalance [mjx-jax]", "brax: inverted_pendulum/mjx",
                           "seed-loop: CartPole-v1 qlearn"}
    many = rows + [_row("jaxrobo", "CartPoleStayUp-v0", n, 1.0 + i, mode=f"learner{i}", backend=b)
                   for i in range(10) for b in ("mjx", "spring") for n in (64, 1024)]
    many += [_row("jaxrobo", "CartPoleStayUp-v0", 1024, 5.0, mode="sarsa", backend="mjx")]  # one size: no curve
    capped = figures.scaling_series(many, "cart-pole")
    assert len(capped) == figures.MAX_SERIES and "jaxrobo: CartPoleStayUp-v0 [mjx] sarsa" not in capped
    assert {k for k in series if not k.startswith("jaxrobo")} <= set(capped)  # every peer stays
    assert [k for k in capped if "learner" in k][:2] == ["jaxrobo: CartPoleStayUp-v0 [mjx] learner0",
                                                          "jaxrobo: CartPoleStayUp-v0 [mjx] learner1"]
    assert len(set(figures.PALETTE)) >= figures.MAX_SERIES  # one colour per series, never repeated
    quad = figures.scaling_series(rows, "quadcopter")  # single sizes only: shown as points
    assert "jaxrobo: QuadcopterGoto-v1 qlearn" in quad and len(quad) == 3  # + crazyflow measured and published

    path = tmp_path / "throughput.json"
    path.write_text(json.dumps({"meta": {"device": "fake"}, "rows": rows}))
    assert throughput.main(["--replot", str(path), "--out", str(tmp_path / "figs")]) == 0
    for name in ("throughput.png", "throughput_cartpole.png", "throughput_quadcopter.png"):
        assert (tmp_path / "figs" / name).stat().st_size > 10_000, name
    assert "x phys" in capsys.readouterr().out
    assert figures.write_figures({"meta": None, "rows": []}, str(tmp_path / "none")) == []


@pytest.mark.slow
def test_playground_and_crazyflow_peers_run_at_a_tiny_size(tmp_path):
    """Each new peer's rollout compiles and steps (2 envs, 2 steps) through the command line, in a process of its
    own (crazyflow needs scipy's array-API mode, set before scipy's first import); skipped rows, with the extra to
    install, where the bench extras are absent."""
    import subprocess

    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": str(tmp_path / "cache"),
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    env.pop("SCIPY_ARRAY_API", None)
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "throughput.py"), "--commands", "none",
           "--time-to-trained", "none", "--n-envs", "2", "--steps", "2", "--repeats", "1", "--envs", "NoSuchEnv-v0",
           "--peers", "playground,crazyflow", "--no-plot", "--out", str(tmp_path)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = {r["suite"]: r for r in json.loads((tmp_path / "throughput.json").read_text())["rows"]
            if r["status"] != "published"}
    for suite, sub, dt, extra in (("playground", 1, 0.01, "bench"), ("crazyflow", 5, 0.002, "bench-quad")):
        row = rows[suite]
        if row["status"] == "skipped":
            assert f"jaxrobo[{extra}]" in row["reason"]
            continue
        assert row["status"] == "ok" and row["steps_per_s"] > 0 and row["n_substeps"] == sub, row
        assert row["physics_dt"] == pytest.approx(dt)
        assert row["physics_steps_per_s"] == pytest.approx(row["steps_per_s"] * sub)
