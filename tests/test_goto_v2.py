"""QuadcopterGoto-v2: registered, its goal_clear feature, the quick check, a tiny train whose summary carries the
greedy arrival rate, benchmarks/goto_learning.py's median over runs, and the run's final table chosen among its
late snapshots as `jaxrobo train` and the benchmark's population choose it (tiny sizes; the figures are a
benchmark)."""
from __future__ import annotations

import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from envs.quadcopter.robot import Obstacles
from envs.quadcopter.goto_v2 import OBS_NAMES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The preset at tiny sizes, without its snapshots: their final choice compiles a greedy flight of its own (a minute
#: of CPU per population shape), and the tests of that choice below use SNAP.
TINY = {"n_envs": 2, "nepisodes": 2, "nsteps": 12, "chunk_steps": 12, "snapshots": 0}


def test_v2_is_registered_with_v1_task_and_its_own_presets():
    assert {"QuadcopterGoto-v1", "QuadcopterGoto-v2"} <= set(jaxrobo.registered())
    v1, v2 = jaxrobo.make("QuadcopterGoto-v1"), jaxrobo.make("QuadcopterGoto-v2")
    assert v2.observation_space().shape == (8,) and OBS_NAMES[-1] == "goal_clear"
    assert v2.num_actions == v1.num_actions == 5
    assert float(v2.default_params.crash_penalty) == 150.0 and float(v1.default_params.crash_penalty) == 50.0
    low, high = v2.state_bounds()
    assert low.shape == high.shape == (8,) and float(high[-1]) == float(v2.default_params.sonar_bound)
    from jaxrobo.training.run import resolve

    spec = resolve("QuadcopterGoto-v2", overrides=TINY)
    assert spec.config.discretiser == "edges" and len(spec.config.edges) == 8


def test_goal_clear_sees_the_grown_obstacle_on_the_way_and_ignores_one_beyond_the_goal():
    env = jaxrobo.make("QuadcopterGoto-v2")
    p = env.default_params
    state = env.reset(jax.random.key(3), p)
    pos = jnp.array([0.0, 0.0, 1.0])

    def clear(goal, cx, cy, radius=0.4):
        obstacles = Obstacles(jnp.array([1], jnp.int32), jnp.array([[cx, cy, 1.5]]), jnp.array([[radius, radius, 1.5]]),
                              jnp.array([True]))
        task = state.task.replace(goal=jnp.asarray(goal, jnp.float32), obstacles=obstacles)
        return float(env._goal_clear(pos, task, p))

    grow = float(p.drone_radius + p.clear_margin)
    assert clear([4.0, 0.0, 1.0], 2.0, 0.0) == pytest.approx(2.0 - 0.4 - grow, abs=1e-4)
    # Beside the line by more than the radius but less than radius + grow: the body would clip it.
    assert clear([4.0, 0.0, 1.0], 2.0, 0.6) < 2.0
    assert clear([4.0, 0.0, 1.0], 2.0, 1.2) == float(p.sonar_range)  # clear of the grown obstacle
    assert clear([1.0, 0.0, 1.0], 2.5, 0.0) == float(p.sonar_range)  # beyond the goal: does not block it
    obs = env.reset(jax.random.key(0), p).obs
    assert obs.shape == (8,) and bool(jnp.all(jnp.isfinite(obs)))


def test_goal_dz_is_read_where_the_climb_stops():
    """goal_dz - dz_lead x vertical velocity: after an "up" step the observed goal_dz is the one the drone settles
    at once it levels off (the velocity loop's lag), within a few cm."""
    env = jaxrobo.make("QuadcopterGoto-v2")
    p = env.default_params
    state = env.reset(jax.random.key(0), p)
    z = lambda s: float(env.robot.read_sensors(s.pipeline_state)["pos"][2])  # noqa: E731
    vz = lambda s: float(env.robot.read_sensors(s.pipeline_state)["vel"][2])  # noqa: E731
    goal_z = float(state.task.goal[2])
    assert float(state.obs[2]) == pytest.approx(goal_z - z(state), abs=1e-5)  # at rest: the drone's own
    up = env.step(state, jnp.int32(3), p)
    assert vz(up) > 0.5
    assert float(up.obs[2]) == pytest.approx(goal_z - z(up) - float(p.dz_lead) * vz(up), abs=1e-5)
    settled = up
    for _ in range(4):  # "forward" commands no climb: the drone levels off
        settled = env.step(settled, jnp.int32(0), p)
    assert abs(vz(settled)) < 0.05
    assert float(up.obs[2]) == pytest.approx(goal_z - z(settled), abs=0.03)
    v1_dz = env.step(state, jnp.int32(3), p.replace(dz_lead=0.0)).obs[2]  # dz_lead 0: v1's goal_dz
    assert float(v1_dz) == pytest.approx(goal_z - z(up), abs=1e-5)


@pytest.mark.slow
def test_tiny_train_summary_has_the_greedy_arrival_rate():
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    spec = resolve("QuadcopterGoto-v2", overrides={**TINY, "eval_episodes": 4})
    res = train(spec.env, spec.config, spec.agent_params)
    assert np.all(np.isfinite(res.returns)) and res.q.shape[-1] == 5
    assert res.eval_success.shape == (1, 4) and res.eval_success.dtype == bool
    s = res.summary()
    assert s["eval_success_rate"] == pytest.approx(res.eval_success.mean())
    assert s["eval_share_of_tables_arriving"] == float(res.eval_success.mean() >= 0.8)
    assert "eval_success_rate" in s and 0.0 <= s["eval_best_table_success_rate"] <= 1.0


def test_benchmark_spread_is_the_median_over_runs():
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    import goto_learning

    s = goto_learning.spread([0.9, 0.1, 0.85, 0.5])
    assert s["median"] == pytest.approx(0.675) and s["min"] == 0.1 and s["max"] == 0.9
    assert s["share_of_runs_at_target"] == 0.5
    with pytest.raises(ValueError, match="one rate per run"):
        goto_learning.spread([])


@pytest.mark.slow
def test_benchmark_tiny_run_reports_every_run_and_their_median(tmp_path, capsys):
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    import goto_learning

    out = tmp_path / "goto.json"
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    assert goto_learning.main(["--env", "QuadcopterGoto-v2", "--runs", "3", "--episodes", "5", "--seed-base", "7",
                               "--select-episodes", "5", "--out", str(out), *sets]) == 0
    data = json.loads(out.read_text())
    per_run = data["fresh_success_per_run"]
    assert data["env"] == "QuadcopterGoto-v2" and data["runs"] == 3 and len(per_run) == 3
    assert all(r * 5 == pytest.approx(round(r * 5)) for r in per_run)  # whole episodes out of 5
    assert data["fresh_success"]["median"] == pytest.approx(float(np.median(per_run)), abs=1e-3)
    assert data["fresh_success"]["min"] == min(per_run) and data["fresh_success"]["max"] == max(per_run)
    assert data["best_of_population"]["fresh_success"] == per_run[data["best_of_population"]["run"]]
    assert data["train_seconds"] > 0
    assert data["seeds"] == [7, 8, 9]
    worst = data["worst_seeds"]
    assert [w["fresh_success"] for w in worst] == sorted(per_run)
    assert all(per_run[data["seeds"].index(w["seed"])] == w["fresh_success"] for w in worst)
    printed = capsys.readouterr().out
    assert "MEDIAN" in printed and "secondary, best of population" in printed and "WORST seeds" in printed
    # --seeds retrains chosen seeds (e.g. a larger run's worst): each run depends on its own seed only.
    again = tmp_path / "again.json"
    assert goto_learning.main(["--env", "QuadcopterGoto-v2", "--seeds", "9,7", "--episodes", "5",
                               "--select-episodes", "5", "--out", str(again), *sets]) == 0
    chosen = json.loads(again.read_text())
    assert chosen["seeds"] == [9, 7] and chosen["runs"] == 2
    assert chosen["fresh_success_per_run"] == [per_run[2], per_run[0]]
    # --fly-set changes only the flights' env: randomisation on with every range at its nominal value flies the
    # nominal physics, so the same tables arrive as often; a key of the learner or the loop is refused.
    flown = tmp_path / "flown.json"
    assert goto_learning.main(["--env", "QuadcopterGoto-v2", "--seeds", "9,7", "--episodes", "5",
                               "--select-episodes", "5", "--out", str(flown), "--fly-set", "randomise=true",
                               *sets]) == 0
    flown = json.loads(flown.read_text())
    assert flown["fly_overrides"] == ["randomise=true"]
    assert flown["fresh_success_per_run"] == chosen["fresh_success_per_run"]
    with pytest.raises(SystemExit):
        goto_learning.main(["--env", "QuadcopterGoto-v2", "--runs", "1", "--fly-set", "alpha=0.1", *sets])
    assert "--fly-set alpha: not a parameter or option" in capsys.readouterr().err


# ---- the run's final table: the best of its final table and late snapshots (Trainer.final_table) --------------
SNAP = {"n_envs": 2, "nepisodes": 20, "nsteps": 12, "chunk_steps": 12, "eval_episodes": 0, "snapshot_episodes": 6}


@pytest.fixture(scope="module")
def snapped():
    """A short Goto-v2 run chunk by chunk: its trainer, final carry and every chunk's (done, table)."""
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    spec = resolve("QuadcopterGoto-v2", overrides=SNAP)
    assert spec.config.snapshots == 4  # the preset's
    trainer = Trainer(spec.env, spec.config)
    ap, ep = spec.agent_params, spec.env.default_params
    runner = jax.jit(trainer.init)(jax.random.key(0), ap, ep)
    chunk = jax.jit(trainer.run_chunk)
    history = []
    for _ in range(trainer.max_chunks()):
        runner = chunk(runner, ap, ep)
        history.append((int(trainer.progress(runner)[0]), np.asarray(runner.agent.q)))
        if history[-1][0] >= spec.config.nepisodes:
            break
    return trainer, runner, history


def test_snapshot_k_is_the_table_at_the_last_chunk_boundary_at_or_before_its_share_of_the_budget(snapped):
    from jaxrobo.training.trainer import SNAPSHOT_SPACING

    trainer, runner, history = snapped
    assert runner.snapshots.shape == (4,) + runner.agent.q.shape
    assert SNAPSHOT_SPACING == 0.05 and trainer.snapshot_points() == [19, 18, 17, 16]  # of 20 episodes per env
    for k, point in enumerate(trainer.snapshot_points(), start=1):
        before = [q for done, q in history if done <= point]
        assert before, f"no chunk ended at or before {point} episodes"
        np.testing.assert_array_equal(np.asarray(runner.snapshots[k - 1]), before[-1], err_msg=f"snapshot {k}")
    assert any(not np.array_equal(np.asarray(s), history[-1][1]) for s in runner.snapshots)


@pytest.mark.slow
def test_final_table_keeps_the_candidate_best_by_the_learning_target(snapped):
    """The choice equals the summary's ranking (success rate, then mean return, the first on a tie) of the
    candidates flown on the same episodes from fold_in(key, 3); a tie keeps the final table."""
    from jaxrobo.task.env import ranking

    trainer, runner, _ = snapped
    key = jax.random.key(0)
    # Candidates that differ: the final table, its negation (greedy flies the worst action), the snapshots.
    runner = runner.replace(snapshots=runner.snapshots.at[0].set(-runner.agent.q))
    chosen, choice = jax.jit(trainer.final_table)(runner, key)
    candidates = np.concatenate([np.asarray(runner.agent.q)[None], np.asarray(runner.snapshots)])
    # Each candidate flown on its own (one compiled flight, called per table), not through final_table's vmap.
    fly = jax.jit(lambda q: trainer.evaluate_episodes(jax.random.fold_in(key, 3), runner.agent.replace(q=q),
                                                      trainer.config.snapshot_episodes))
    flights = [fly(jnp.asarray(q)) for q in candidates]
    per_table = {"mean_return": np.stack([np.asarray(f["return"]) for f in flights]),
                 "success_rate": np.stack([np.asarray(f["arrived"]) for f in flights])}
    assert int(choice) == ranking(trainer.env.learning_target).best_table(per_table)
    np.testing.assert_array_equal(np.asarray(chosen.agent.q), candidates[int(choice)])
    same = runner.replace(snapshots=jnp.broadcast_to(runner.agent.q, runner.snapshots.shape))
    assert int(jax.jit(trainer.final_table)(same, key)[1]) == 0


def test_snapshots_need_a_shared_table_and_stay_in_range():
    from jaxrobo.core.config import ConfigError
    from jaxrobo.training.run import resolve

    with pytest.raises(ConfigError, match="snapshots=4 needs shared_table=true"):
        resolve("QuadcopterGoto-v2", overrides={"shared_table": False})
    with pytest.raises(ConfigError, match="snapshots"):
        resolve("QuadcopterGoto-v2", overrides={"snapshots": 11})
    assert resolve("QuadcopterGoto-v2", overrides={"shared_table": False, "snapshots": 0}).config.snapshots == 0


@pytest.mark.slow
def test_train_and_the_benchmark_population_keep_the_same_table(tmp_path):
    """`jaxrobo train --seed 9` and goto_learning's vmapped population of that seed end with the same table, and
    the summary says which candidate it is. (A population of several seeds matches it too, but only to the
    last bits of float32 here: XLA vectorises the batched physics differently.)"""
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    import goto_learning

    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    sizes = {k: v for k, v in SNAP.items() if k != "eval_episodes"}
    _, _, q, _ = goto_learning.train("QuadcopterGoto-v2", [9], sizes)
    spec = resolve("QuadcopterGoto-v2", overrides={**SNAP, "seed": 9})
    res = train(spec.env, spec.config, spec.agent_params)
    np.testing.assert_array_equal(res.q[0], q[0])
    assert res.summary()["final_table_choice"] in range(5)
