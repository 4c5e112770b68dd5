"""Sweeps: parsing and grouping, and a vmapped sweep gives exactly the numbers of separate single runs."""
from __future__ import annotations

import argparse
import csv
import json
import os

import jax
import numpy as np
import pytest

from jaxrobo.training import sweep
from jaxrobo.core.config import ConfigError
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer

ENV = "CartPoleStayUp-v0"
FAST = {"xla_backend_optimization_level": 0}  # compile fast; sweep and single runs use the same options
TINY = ["--n-envs", "2", "--nepisodes", "5", "--nsteps", "40", "--set", "chunk_steps=50"]


def test_parse_grid_ranges_and_points():
    assert sweep.parse_grid(["alpha=0.1,0.3", "number_splits=6"]) == {"alpha": [0.1, 0.3], "number_splits": [6]}
    assert sweep.parse_ranges(["alpha=0.05:0.9", "epsilon_discount=0.9:0.999:log"]) == {
        "alpha": (0.05, 0.9, False), "epsilon_discount": (0.9, 0.999, True)}
    assert len(sweep.grid_points({"a": [1, 2, 3], "b": [4, 5]})) == 6
    pts = sweep.random_points({"alpha": (0.05, 0.9, False), "gamma": (0.5, 0.99, True)}, 50, seed=1)
    assert len(pts) == 50 and all(0.05 <= p["alpha"] <= 0.9 and 0.5 <= p["gamma"] <= 0.99 for p in pts)
    assert pts == sweep.random_points({"alpha": (0.05, 0.9, False), "gamma": (0.5, 0.99, True)}, 50, seed=1)
    for bad in (["alpha"], ["alpha="]):
        with pytest.raises(ConfigError, match="--grid"):
            sweep.parse_grid(bad)
    with pytest.raises(ConfigError, match="--range"):
        sweep.parse_ranges(["alpha=0.9:0.1"])


def test_points_from_args_grid_times_random():
    ns = argparse.Namespace(grid=["gamma=0.9,0.99", "alpha=0.05:0.9"], ranges=None, random=3, seed=0)
    pts = sweep.points_from_args(ns)
    assert len(pts) == 6 and {p["gamma"] for p in pts} == {0.9, 0.99}
    with pytest.raises(ConfigError, match="--random"):
        sweep.points_from_args(argparse.Namespace(grid=None, ranges=["alpha=0.1:0.2"], random=0, seed=0))


def test_classify_and_grouping():
    assert sweep.classify(ENV, "alpha").where == "agent"
    assert sweep.classify(ENV, "pos_step").where == "env"
    assert sweep.classify(ENV, "number_splits").static
    assert sweep.classify(ENV, "running_step").static
    with pytest.raises(ConfigError, match="alpa"):
        sweep.classify(ENV, "alpa")
    with pytest.raises(ConfigError, match="--seeds"):
        sweep.classify(ENV, "seed")
    with pytest.raises(ConfigError, match="alpha"):
        sweep.plan_groups(ENV, [{"alpha": 7.0}])
    _, _, _, groups = sweep.plan_groups(ENV, [{"alpha": a, "number_splits": s} for a in (0.1, 0.5) for s in (6, 8)])
    assert sorted(len(v) for v in groups.values()) == [2, 2] and len(groups) == 2


def test_cli_rejects_bad_flags(tmp_path, capsys):
    assert sweep.main(["--grid", "alpa=0.1", "--out", str(tmp_path)]) == 2
    assert "alpa" in capsys.readouterr().err
    assert sweep.main(["--seeds", "0", "--out", str(tmp_path)]) == 2


@pytest.fixture(scope="module")
def cli_sweep(tmp_path_factory):
    """A 2 × 2 grid (learner alpha × env pos_step) × 2 seeds through `jaxrobo sweep`, compiled once."""
    out = tmp_path_factory.mktemp("sweep")
    rc = sweep.main(["--env", ENV, "--agent", "qlearn", "--grid", "alpha=0.1,0.5", "--grid", "pos_step=0.016,0.03",
                     "--seeds", "2", "--seed", "3", "--eval-episodes", "2", *TINY, "--out", str(out)],
                    compiler_options=FAST)
    assert rc == 0
    with open(out / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    return out, rows


def test_cli_writes_csv_heatmap_and_best(cli_sweep):
    out, rows = cli_sweep
    assert len(rows) == 8
    assert {(float(r["alpha"]), float(r["pos_step"]), int(r["seed"])) for r in rows} == {
        (a, p, s) for a in (0.1, 0.5) for p in (0.016, 0.03) for s in (3, 4)}
    assert all(int(r["episodes_done"]) >= 5 and 0 < float(r["eval_mean_length"]) <= 1000 for r in rows)
    assert os.path.exists(out / "heatmap_alpha_pos_step.png")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best"]["metric"] == "final_return" and summary["n_rows"] == 8


def test_sweep_equals_single_runs(cli_sweep):
    """Every row equals a separate run of the same learner, env parameters and seed (jit of Trainer, no vmap)."""
    _, rows = cli_sweep
    spec = resolve(ENV, "default", {"n_envs": 2, "nepisodes": 5, "nsteps": 40, "chunk_steps": 50}, agent="qlearn")
    trainer = Trainer(spec.env, spec.config)
    init = jax.jit(trainer.init, compiler_options=FAST)
    chunk = jax.jit(trainer.run_chunk, compiler_options=FAST)
    for r in rows:
        ap = spec.agent_params.replace(alpha=float(r["alpha"]))
        ep = spec.env.default_params.replace(pos_step=float(r["pos_step"]))
        runner = init(jax.random.key(int(r["seed"])), ap, ep)
        for _ in range(trainer.max_chunks()):
            runner = chunk(runner, ap, ep)
            if int(runner.episode.min()) >= 5:
                break
        returns = np.asarray(runner.returns, np.float32)
        lengths = np.asarray(runner.lengths, np.float32)
        assert int(np.asarray(runner.env_steps).sum()) == int(r["env_steps"])
        np.testing.assert_allclose(returns[:, -5:].mean(), float(r["final_return"]), rtol=1e-6)
        np.testing.assert_allclose(lengths.mean(), float(r["mean_length"]), rtol=1e-6)
        np.testing.assert_allclose(returns.max(), float(r["highest_reward"]), rtol=1e-6)
