"""Summaries, the printed summary and sweep metrics pick "best" the way the task's learning target says: for a
minimum-time task (reward -1 a step) the shortest episodes and tables, not the longest."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.cli import _training_figures
from jaxrobo.tabular.learner import AgentParams
from jaxrobo.task.env import LearningTarget, Ranking, ranking
from jaxrobo.training.summary import TrainResult, best_window
from jaxrobo.training.sweep.running import SweepResult, _best_window, higher_is_better
from jaxrobo.training.trainer import TrainConfig

#: A minimum-time task's target, as an acrobot would declare it: reward -1 a step, so a higher return is a
#: shorter swing-up.
FAST = LearningTarget("fast", "mean_return", -150.0, "mean greedy return >= -150 (swing up within 150 steps)")
#: The same task stated on the length.
SHORT = LearningTarget("short", "mean_length", 150.0, "mean greedy episode length <= 150", better="lower")


def _min_time_result(target: LearningTarget) -> TrainResult:
    """Two envs of 150 episodes: env 0 learns (500 steps down to 100), env 1 gets worse; every return is
    -length. Three evaluated tables of mean length 400, 120 and 500."""
    down = np.linspace(500, 100, 150).round()
    lengths = np.stack([down, down[::-1]]).astype(np.int32)
    ev = np.array([[400, 400], [110, 130], [500, 500]])
    return TrainResult(
        "MinTime-v0", TrainConfig(n_envs=2, nepisodes=150), AgentParams(), -lengths.astype(np.float32), lengths,
        np.ones_like(lengths, bool), np.ones(150, np.float32), np.zeros(2, np.int32), int(lengths.sum()),
        np.zeros((2, 1, 2, 2)), 0.0, 1.0, eval_returns=-ev.astype(np.float32), eval_lengths=ev,
        learning_target=target)


@pytest.mark.parametrize("target", [FAST, SHORT])
def test_a_minimum_time_summary_picks_the_shortest_window_and_table(target):
    r = _min_time_result(target)
    s = r.summary()
    figure = "return" if target is FAST else "length"
    window = s[f"best_100_window_mean_{figure}"]
    # The best 100 consecutive episodes are env 0's last 100 and env 1's first 100: the short ones.
    short = np.linspace(500, 100, 150).round()[-100:].mean()
    assert window == pytest.approx(-short if target is FAST else short)
    assert s["eval_best_table"] == 1 and s["eval_best_table_mean_length"] == 120.0
    assert s["eval_best_table_mean_return"] == -120.0
    assert s[f"eval_share_of_tables_{target.name}"] == pytest.approx(1 / 3)
    assert s["best_ranked_by"] == ("return, higher is better" if target is FAST else "length, lower is better")
    longest = np.sort(np.linspace(500, 100, 150).round())[-100:].mean()
    assert s["best_100_mean_length"] == pytest.approx(longest)  # the seed's figure keeps its meaning
    line = _training_figures(s)
    assert f"best 100-episode window of mean {figure}: {window:.1f}" in line and s["best_ranked_by"] in line


def test_without_a_target_longer_is_better_as_in_the_seed():
    s = _min_time_result(FAST)
    s = dataclasses.replace(s, learning_target=None).summary()
    assert s["eval_best_table"] == 2 and s["eval_best_table_mean_length"] == 500.0
    assert s["best_100_window_mean_length"] == pytest.approx(np.linspace(500, 100, 150).round()[:100].mean())


def test_the_best_table_breaks_a_success_tie_by_return_and_validates_the_direction():
    rank = ranking(LearningTarget("arriving", "success_rate", 0.8, "arrive"))
    per_table = {"success_rate": np.array([[1, 1], [1, 1], [0, 1]]),
                 "mean_return": np.array([[1.0, 1.0], [5.0, 5.0], [9.0, 9.0]])}
    assert rank.best_table(per_table) == 1
    with pytest.raises(ValueError, match="better='sideways'"):
        LearningTarget("x", "mean_length", 1.0, "", better="sideways")
    with pytest.raises(ValueError, match="better='lower'"):
        LearningTarget("x", "success_rate", 0.5, "", better="lower")


@pytest.mark.parametrize("higher", [True, False])
def test_the_host_and_the_traced_choice_of_a_table_follow_one_rule(higher):
    """:meth:`Ranking.best_of` on numpy (a run's evaluated tables) and traced on jax.numpy (its late snapshots,
    ``Trainer.final_table``): the best score in the target's direction, a tie by the higher return, then the
    first; a NaN ranks last; without the score, the higher return alone."""
    import jax
    import jax.numpy as jnp

    rank = Ranking("return", "success_rate", higher)
    nan = float("nan")
    cases = [  # score, return, the best table
        ([0.5, 0.9, 0.9, 0.1], [3.0, 1.0, 2.0, 9.0], 2 if higher else 3),
        ([0.9, 0.9], [2.0, 2.0], 0),
        ([nan, 0.2, 0.4], [9.0, 1.0, 1.0], 2 if higher else 1),
        ([0.2, 0.2], [nan, 1.0], 1),
        (None, [1.0, 4.0, 4.0, 2.0], 1),
    ]
    for score, ret, best in cases:
        assert rank.best_of(None if score is None else np.array(score), np.array(ret)) == best, (score, ret)
        traced = jax.jit(lambda s, r: rank.best_of(s, r, jnp))(None if score is None else jnp.array(score, jnp.float32),
                                                              jnp.array(ret, jnp.float32))
        assert int(traced) == best, (score, ret)
        if score is not None:
            table = {"success_rate": np.array(score)[:, None], "mean_return": np.array(ret)[:, None]}
            assert rank.best_table(table) == best


@pytest.mark.parametrize("rank", [Ranking("return", "mean_return", True), Ranking("length", "mean_length", False)])
def test_the_sweeps_window_is_the_summarys_on_the_device(rank):
    rng = np.random.default_rng(0)
    figure = rng.integers(1, 500, size=(3, 2, 130)).astype(np.float32)  # [rows, envs, episodes]
    count = np.array([[130, 130], [40, 130], [0, 7]])  # a run-wide budget: envs record different numbers
    got = np.asarray(_best_window(jnp.asarray(figure), jnp.asarray(count), rank))
    for row in range(3):
        mask = np.arange(130)[None, :] < count[row][:, None]
        assert got[row] == pytest.approx(best_window(figure[row], mask, rank), rel=1e-5)


def test_a_sweep_ranks_lengths_the_targets_way():
    short = Ranking("length", "mean_length", False)
    rows = [{"config": c, "seed": 0, "alpha": a, "final_length": L, "final_return": -L, "physics_nan_episodes": n}
            for c, a, L, n in ((0, 0.1, 300.0, 0), (1, 0.2, 120.0, 3))]
    result = SweepResult("MinTime-v0", ["alpha"], rows, [], 1.0, short)
    assert result.best("final_length")["alpha"] == 0.2 and result.best("final_length")["higher"] is False
    assert result.best("final_return")["alpha"] == 0.2
    assert result.best("physics_nan_episodes")["alpha"] == 0.1
    assert higher_is_better("final_length", Ranking("length", "mean_length", True))
    assert higher_is_better("best_100_window", short) is False


def test_a_deep_runs_best_evaluation_follows_the_target():
    """PPO/SAC keep a best policy: for a minimum-time target the evaluation with the shortest episodes."""
    from jaxrobo.deep.training import best_index

    points = [{"return": np.array([-300.0, -280.0]), "length": np.array([300, 280])},
              {"return": np.array([-90.0, -110.0]), "length": np.array([90, 110])},
              {"return": np.array([-500.0, -500.0]), "length": np.array([500, 500])}]
    assert best_index(points, SHORT) == 1 and best_index(points, FAST) == 1
    longest = LearningTarget("up", "mean_length", 500.0, "kept up")
    assert best_index(points, longest) == 2
    assert best_index(points) == 1  # no target: the highest return, as before


@pytest.mark.parametrize("higher", [True, False])
def test_the_summary_figures_are_their_per_env_definitions_whatever_the_blocks_and_threads(monkeypatch, higher):
    """The seed's figures and the best window (computed over blocks of envs, by threads) equal their per-env
    definitions, written here env by env; the numbers are the same bit for bit for any block size and thread
    count."""
    from jaxrobo.training import summary

    rng = np.random.default_rng(3)
    n_envs, width = 23, 240
    count = rng.integers(0, width + 1, n_envs)
    count[:4] = [0, 1, 100, width]
    recorded = np.arange(width)[None, :] < count[:, None]
    lengths = np.where(recorded, rng.integers(1, 1000, (n_envs, width)), 0).astype(np.int32)
    returns = np.where(recorded, rng.normal(0.0, 50.0, (n_envs, width)), 0.0).astype(np.float32)
    rank = Ranking("length", "mean_length", higher)

    def window(e: int) -> float:
        x, w = lengths[e, :count[e]].astype(np.float64), min(100, int(count[e]))
        means = [x[j:j + w].mean() for j in range(count[e] - w + 1)]
        return max(means) if higher else min(means)

    has = count > 0
    expected = {
        "highest_reward_mean": np.mean([float(returns[e, :count[e]].max()) for e in np.flatnonzero(has)]),
        "overall_mean_length": lengths.sum() / count.sum(),
        "best_100_mean_length": np.mean([np.sort(lengths[e, :count[e]])[-100:].mean() for e in np.flatnonzero(has)]),
        "final_100_mean_return": np.concatenate([returns[e, count[e] - min(100, count[e]):count[e]]
                                                 for e in np.flatnonzero(has)]).astype(np.float64).mean()}
    expected_window = np.mean([window(e) for e in np.flatnonzero(has)])
    got = []
    for block, threads in ((summary.FIGURE_BLOCK_ENVS, 1), (5, 1), (5, 3), (1, 4)):
        monkeypatch.setattr(summary, "FIGURE_BLOCK_ENVS", block)
        monkeypatch.setattr("jaxrobo.core.environ.usable_cores", lambda threads=threads: threads)
        figures = summary._masked_figures(returns, lengths, recorded)
        for name, value in expected.items():
            assert figures[name] == pytest.approx(value, rel=1e-9), name
        best = best_window(lengths, recorded, rank)
        assert best == pytest.approx(expected_window, rel=1e-9)
        got.append((figures, best))
    assert all(repr(g) == repr(got[0]) for g in got)
