"""benchmarks/learning_targets.py judges each run as `jaxrobo train --seed S` judges it (tiny sizes on the closed-form
cart-pole: per-env tables, so the best table is chosen and flown again on fresh episodes)."""
import json
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETS = {"env.backend": "analytic", "n_envs": 4, "nepisodes": 3, "nsteps": 30, "chunk_steps": 30,
        "eval_envs": 2, "eval_episodes": 3}


@pytest.fixture(scope="module")
def learning_targets():
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    import learning_targets

    return learning_targets


def _sets():
    return [f"--set={k}={v}" for k, v in SETS.items()]


@pytest.mark.slow
def test_both_budgets_are_judged_as_jaxrobo_train_judges_a_run(learning_targets, tmp_path):
    out = tmp_path / "lt.json"
    assert learning_targets.main(["--envs", "CartPoleStayUp-v0", "--runs", "2", "--seed-base", "5",
                                  "--out", str(out), *_sets()]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["budget"] for r in rows] == ["episodes", "steps"]
    episodes, steps = rows
    # the step budget: the median experience of the episode budget, in whole chunks of every env
    assert steps["total_steps"] % (SETS["n_envs"] * SETS["chunk_steps"]) == 0
    assert steps["total_steps"] >= sorted(episodes["env_steps"])[0]
    for r in rows:
        assert r["seeds"] == [5, 6] and len(r["score"]) == 2
        assert r["met"] == [s >= r["threshold"] for s in r["score"]]
        assert r["share_met"] == sum(r["met"]) / 2
    # seed 6's figure is what `jaxrobo train --seed 6` reports: its best table's mean length on fresh episodes
    from jaxrobo.cli import main

    run = tmp_path / "run"
    assert main(["train", "--env", "CartPoleStayUp-v0", "--seed", "6", "--no-progress", "--out", str(run),
                 *_sets()]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["selected_table_fresh_mean_length"] == pytest.approx(episodes["score"][1], abs=1e-4)


def test_a_given_step_budget_trains_only_the_step_budget_runs(learning_targets, tmp_path):
    out = tmp_path / "lt.json"
    assert learning_targets.main(["--envs", "CartPoleStayUp-v0", "--runs", "1", "--total-steps", "240",
                                  "--out", str(out), *_sets()]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["budget"] == "steps" and row["total_steps"] == 240 and row["env_steps"] == [240]
    with pytest.raises(SystemExit):
        learning_targets.main(["--envs", "CartPoleStayUp-v0", "--total-steps", "0"])
    with pytest.raises(SystemExit):
        learning_targets.main(["--envs", "CartPoleStayUp-v0", "--set", "total_steps=100"])
