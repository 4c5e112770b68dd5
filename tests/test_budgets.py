"""The run's budget (:attr:`jaxrobo.training.trainer.Trainer.budget`): the seed's per-env episode budget (the
default, unchanged), the step budget ``total_steps`` and the run-wide episode budget ``total_episodes``, each
independent of the chunk length, with the useful share of env slots reported."""
from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest

from jaxrobo.core.config import ConfigError
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer
from jaxrobo.training.train import train

SMALL = dict(n_envs=8, nepisodes=5, nsteps=40, chunk_steps=25, eval_episodes=2, eval_envs=2, backend="analytic")


def _run(**overrides):
    spec = resolve("CartPoleStayUp-v0", overrides={**SMALL, **overrides})
    return spec, train(spec.env, spec.config, spec.agent_params)


def test_the_step_budget_keeps_every_slot_busy_and_counts_whole_episodes():
    spec, r = _run(total_steps=8 * 100, chunk_steps=25)
    t = Trainer(spec.env, spec.config)
    assert t.budget == "steps" and t.steps_per_env == 100 and t.max_chunks() == 4
    assert r.env_steps == 800 and r.slot_steps == 800 and r.useful_share == 1.0
    done = np.asarray(r.episodes_done)
    # records hold whole episodes only: each env's recorded lengths sum to at most its 100 steps
    for e in range(8):
        n = int(done[e])
        assert n >= 1 and int(r.lengths[e, :n].sum()) <= 100
        assert np.all(r.lengths[e, :n] > 0) and np.all(r.lengths[e, n:] == 0)
    s = r.summary()
    assert s["budget"] == "steps" and s["total_steps"] == 800 and s["useful_share"] == 1.0
    assert s["episodes_finished"] >= s["episodes_recorded"] >= 8


def test_the_step_budget_does_not_depend_on_the_chunk_length():
    _, a = _run(total_steps=8 * 90, chunk_steps=25)
    _, b = _run(total_steps=8 * 90, chunk_steps=7)
    for name in ("q", "returns", "lengths", "terminated", "env_steps", "eval_returns"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    # 90 steps per env asked in chunks of at most 25: four chunks of 23 (92 slots), not three of 25 and a fourth
    # mostly idle (100 slots); chunks of at most 7: thirteen of 7 (91 slots)
    assert a.config.chunk_steps == 23 and a.slot_steps == 8 * 92 and a.useful_share == pytest.approx(90 / 92)
    assert b.config.chunk_steps == 7 and b.slot_steps == 8 * 91


def test_the_step_budget_is_stepped_with_fewer_idle_slots_than_chunks():
    """Whatever chunk_steps asks, resolve cuts each env's budget into as many chunks as it gives, each as short as
    that count needs: fewer idle slots per env than chunks; resolving the result again gives it back (--resume)."""
    for n_envs, total, chunk in ((64, 200_000, 1000), (7, 1000, 13), (3, 5, 100), (5, 1_000_003, 999)):
        c = resolve("CartPoleStayUp-v0", overrides={"n_envs": n_envs, "total_steps": total,
                                                     "chunk_steps": chunk}).config
        per_env = -(-total // n_envs)
        n_chunks = -(-per_env // chunk)
        assert c.chunk_steps <= chunk and -(-per_env // c.chunk_steps) == n_chunks
        assert 0 <= n_chunks * c.chunk_steps - per_env < n_chunks
        again = resolve("CartPoleStayUp-v0", overrides={"n_envs": n_envs, "total_steps": total,
                                                         "chunk_steps": c.chunk_steps}).config
        assert again.chunk_steps == c.chunk_steps


def test_the_run_episode_budget_counts_episodes_of_the_whole_run():
    spec, r = _run(total_episodes=30, shared_table=True, chunk_steps=10)
    assert Trainer(spec.env, spec.config).budget == "run_episodes"
    total = int(r.episodes_finished)
    # every env keeps feeding the table until the run has 30 episodes; the step that crosses may add a few
    assert 30 <= total < 30 + 8
    assert r.summary()["budget"] == "run_episodes"


def test_the_episode_budget_is_the_default_and_unchanged():
    spec, r = _run()
    assert Trainer(spec.env, spec.config).budget == "episodes"
    assert np.all(np.asarray(r.episodes_done) == 5) and r.recorded() is None
    assert 0 < r.useful_share <= 1.0


@pytest.mark.parametrize("overrides, fragment", [
    (dict(total_steps=100, total_episodes=10), "give one run-wide budget"),
    (dict(total_steps=-1), "total_steps"),
    (dict(total_episodes=2**31 - 2), "total_episodes"),
    (dict(total_steps=2**40, n_envs=2), "steps per env"),
])
def test_bad_budgets_are_refused_naming_the_key(overrides, fragment):
    with pytest.raises(ConfigError, match=fragment):
        resolve("CartPoleStayUp-v0", overrides={**SMALL, **overrides})


def test_the_cli_reports_useful_share_and_wall_split(tmp_path, capsys, monkeypatch):
    from jaxrobo.cli import main

    out = tmp_path / "run"
    called = time.perf_counter()
    rc = main(["train", "--env", "CartPoleStayUp-v0", "--set", "env.backend=analytic", "--n-envs", "4",
               "--total-steps", "200", "--set", "chunk_steps=25", "--set", "nsteps=40", "--set", "eval_episodes=2",
               "--no-progress", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "100.0% of the 200 env slots stepped were useful" in text
    assert re.search(r"wall \d+\.\d s: start-up \d+\.\d s, compile", text)
    # run inside another program (here pytest), the wall and its start-up count from the call, not from the
    # program's start (a CI log once read "wall 617.3 s: start-up 609.3 s" for a 12 s run)
    wall, startup = map(float, re.search(r"wall (\d+\.\d) s: start-up (\d+\.\d) s", text).groups())
    assert startup <= wall <= time.perf_counter() - called + 0.1
    s = json.loads((out / "summary.json").read_text())
    assert s["useful_share"] == 1.0 and s["env_slots"] == 200
    for key in ("startup_seconds", "compile_seconds", "run_seconds", "eval_seconds", "write_seconds"):
        assert s[key] >= 0
    # live TensorBoard scalars were written during the run (flushed each chunk), one point per chunk
    events = list((out / "tensorboard").glob("events.out.tfevents.*"))
    assert events
    from jaxrobo.io.results import read_scalars

    scalars = read_scalars(str(out / "tensorboard"))
    assert [v for _, v in scalars["progress/useful_share"]] == [1.0, 1.0]  # 200 steps / 4 envs: 2 chunks of 25
    # `jaxrobo plot --scalars`: those scalars as a picture (TensorBoard's page without a browser)
    assert main(["plot", str(out), "--scalars"]) == 0
    assert (out / "scalars.png").stat().st_size > 5000
    # a record cut in the middle (a writer mid-flush, or a damaged file) ends the reading, never raises
    assert "episode/reward_mean" in scalars  # the per-episode scalars written at the end, beside the live ones
    cut = tmp_path / "cut"
    cut.mkdir()
    live = next(e for e in events if b"progress/useful_share" in e.read_bytes())
    data = live.read_bytes()
    (cut / live.name).write_bytes(data[:-7])  # the last record torn
    assert read_scalars(str(cut))["progress/useful_share"] == scalars["progress/useful_share"]
    (cut / live.name).write_bytes(data[: len(data) - 60])  # torn inside the last chunk's records
    assert len(read_scalars(str(cut)).get("progress/steps_per_second", [])) < 2
    (cut / live.name).write_bytes(data[:40] + b"\xff" * 64)
    assert read_scalars(str(cut)) == {}
    # a file is read up to MAX_TB_FILE bytes only: what lies beyond (here the second chunk's records) is not read
    import jaxrobo.io.results as results

    (cut / live.name).write_bytes(data)
    monkeypatch.setattr(results, "MAX_TB_FILE", len(data) - 60)
    assert len(read_scalars(str(cut)).get("progress/steps_per_second", [])) < 2



def test_a_run_directory_computes_its_episode_stats_once_for_the_csv_and_tensorboard(tmp_path):
    """``write_episodes`` returns the :func:`jaxrobo.io.results.episode_stats` it wrote to ``episode_stats.csv``,
    and ``save_run`` hands them to TensorBoard's per-episode scalars instead of computing them again; for every env
    recording every episode and under a run-wide budget (envs with different counts), the returned columns are
    ``episode_stats``' and the scalars are the CSV's means and epsilon."""
    from jaxrobo.io.results import episode_stats, read_columns, read_scalars, write_episodes, write_tensorboard

    rng = np.random.default_rng(7)
    returns = (rng.random((67, 30)) * 500).astype(np.float32)
    lengths = rng.integers(1, 1000, (67, 30)).astype(np.int32)
    terminated, epsilon = lengths < 900, np.linspace(1, 0.1, 30, dtype=np.float32)
    for name, done in (("full", None), ("budget", rng.integers(0, 31, 67))):
        out = tmp_path / name
        stats = write_episodes(str(out), returns, lengths, terminated, epsilon, episodes_done=done)
        expected = episode_stats(returns, lengths, epsilon, np.full(67, 30) if done is None else done)
        assert len(stats) == len(expected)
        for got, want in zip(stats, expected):
            np.testing.assert_array_equal(got, want)
        write_tensorboard(str(out), stats)
        csv = read_columns(str(out / "episode_stats.csv"), ("return_mean", "length_mean", "epsilon"))
        scalars = read_scalars(str(out / "tensorboard"))
        for tag, column in (("reward_mean", "return_mean"), ("length_mean", "length_mean"), ("epsilon", "epsilon")):
            np.testing.assert_allclose([v for _, v in scalars[f"episode/{tag}"]], csv[column], rtol=1e-5)
