"""The vectorised trainer: records, the seed's loop rules, every learner, shared tables, determinism."""
from __future__ import annotations

import numpy as np
import pytest

from jaxrobo.training.run import resolve
from jaxrobo.training.train import train

TINY = dict(n_envs=4, nepisodes=6, nsteps=40, chunk_steps=50, eval_episodes=0,
            bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])


def _run(**overrides):
    spec = resolve("CartPoleStayUp-v0", overrides={**TINY, **overrides})
    return train(spec.env, spec.config, spec.agent_params)


@pytest.fixture(scope="module")
def qlearn_run():
    return _run(eval_episodes=2, eval_envs=2)


def test_every_episode_of_every_env_is_recorded(qlearn_run):
    r = qlearn_run
    assert r.returns.shape == r.lengths.shape == r.terminated.shape == (4, 6)
    assert np.all(r.lengths >= 1) and np.all(r.lengths <= 40)
    np.testing.assert_array_equal(r.returns, r.lengths)  # reward 1 per step, falling step included
    assert r.env_steps == int(r.lengths.sum())
    assert np.all(r.terminated | (r.lengths == 40))  # an episode ends by failure or by the nsteps cap
    assert r.q.shape == (4, 1, 3 * 6 * 8 * 10, 4)
    assert r.eval_lengths.shape == (2, 2)


def test_summary_has_the_seeds_figures(qlearn_run):
    s = qlearn_run.summary()
    lengths = qlearn_run.lengths
    assert s["highest_reward_max"] == lengths.max()
    assert s["overall_mean_length"] == pytest.approx(lengths.mean())
    assert s["best_100_mean_length"] == pytest.approx(lengths.mean())  # fewer than 100 episodes: all of them
    assert s["physics_nan_episodes"] == 0 and s["env_steps_per_second"] > 0


def test_epsilon_is_recorded_per_episode(qlearn_run):
    d = float(qlearn_run.agent_params.epsilon_discount)
    np.testing.assert_allclose(qlearn_run.epsilon, 0.1 * d ** np.arange(1, 7), rtol=1e-5)


def test_same_seed_gives_identical_results(qlearn_run):
    again = _run(eval_episodes=2, eval_envs=2)
    np.testing.assert_array_equal(again.returns, qlearn_run.returns)
    np.testing.assert_array_equal(again.q, qlearn_run.q)
    other = _run(seed=1)
    assert not np.array_equal(other.returns, qlearn_run.returns)


def test_results_do_not_depend_on_the_chunk_length(qlearn_run):
    np.testing.assert_array_equal(_run(chunk_steps=17).returns, qlearn_run.returns)


@pytest.mark.parametrize("group", [3, 2])
def test_stepping_envs_in_groups_changes_nothing(qlearn_run, group):
    """``env_group``: the 4 envs stepped as groups of 3 and 1, or 2 and 2 (as GPUs step large MJX batches), give
    the same run as all 4 at once."""
    grouped = _run(eval_episodes=2, eval_envs=2, env_group=group)
    np.testing.assert_array_equal(grouped.returns, qlearn_run.returns)
    np.testing.assert_array_equal(grouped.lengths, qlearn_run.lengths)
    np.testing.assert_array_equal(grouped.q, qlearn_run.q)


def test_a_shared_table_run_steps_its_envs_in_groups_with_the_same_values():
    whole, grouped = (_run(shared_table=True, env_group=g) for g in (0, 3))
    np.testing.assert_array_equal(grouped.returns, whole.returns)
    np.testing.assert_array_equal(grouped.q, whole.q)


def _learned(**overrides):
    """The default preset, shortened, on the closed-form backend (300 episodes take seconds): the run, and its
    mean return over the first and the last 30 episodes."""
    spec = resolve("CartPoleStayUp-v0", overrides={"n_envs": 16, "nepisodes": 300, "chunk_steps": 500,
                                                   "eval_episodes": 0, "backend": "analytic", **overrides})
    r = train(spec.env, spec.config, spec.agent_params)
    return r, r.returns[:, :30].mean(), r.returns[:, -30:].mean()


@pytest.mark.parametrize("agent", ["sarsa", "expected_sarsa", "double_q"])
def test_each_learner_trains(agent):
    """Each learner's return improves. Double Q-learning's per-env tables learn too slowly on the cart-pole for
    300 episodes (updated half as often each, and evaluated by the other table), so it learns here with the
    16 envs' one shared table, and its per-env run updates both of every env's tables."""
    if agent == "double_q":
        r = _run(agent=agent)
        assert r.q.shape[:2] == (4, 2) and all(np.count_nonzero(r.q[i, t]) for i in range(4) for t in range(2))
        assert np.count_nonzero(r.q) <= r.env_steps
    r, first, last = _learned(agent=agent, shared_table=agent == "double_q")
    assert r.q.shape[1] == (2 if agent == "double_q" else 1)
    assert np.isfinite(r.q).all() and last > 1.5 * first, (first, last)


def test_shared_table_mode_learns_one_table():
    """Every env's updates go to the one table, and it learns."""
    r, first, last = _learned(shared_table=True)
    assert r.q.shape[0] == 1 and np.isfinite(r.q).all() and last > 1.5 * first, (first, last)


def test_seed_preset_runs_with_seed_compat_learner():
    spec = resolve("CartPoleStayUp-v0", "seed", overrides=dict(n_envs=2, nepisodes=3, nsteps=30, chunk_steps=40,
                                                             eval_episodes=0))
    r = train(spec.env, spec.config, spec.agent_params)
    assert r.q.shape[2] == 51 * 41 * 15 * 61
    visited = np.count_nonzero(r.q)
    assert 0 < visited <= r.env_steps  # the dict of the seed only holds visited entries; so does this table


def test_learning_improves_the_return():
    _, first, last = _learned()
    assert last > 1.5 * first, (first, last)


@pytest.mark.parametrize("agent", ["qlearn", "sarsa"])
def test_gathered_resets_equal_resetting_every_env(agent):
    """Only the done envs are reset (gathered, up to ``reset_capacity`` a step, all of them beyond): the carry
    is bit for bit the one of resetting every env and selecting, on both paths (capacity 2 of 12 is exceeded
    at times by the short early episodes, so the fallback runs too)."""
    import jax

    from jaxrobo.training.trainer import Trainer

    spec = resolve("CartPoleStayUp-v0", overrides={**TINY, "n_envs": 12, "backend": "analytic"}, agent=agent)
    ap, ep = spec.agent_params, spec.env.default_params
    carries = []
    for capacity in (2, 12):  # 12 = every env, the plain select
        trainer = Trainer(spec.env, spec.config)
        trainer.reset_capacity = capacity
        runner = trainer.init(jax.random.key(5), ap, ep)
        for _ in range(4):
            runner = jax.jit(trainer.run_chunk)(runner, ap, ep)
        carries.append(jax.tree.leaves(jax.tree.map(
            lambda x: jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x, runner)))
    assert int(np.asarray(carries[0][0]).size) > 0
    for a, b in zip(*carries):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("agent,extra", [("qlearn", {}), ("sarsa", {}), ("double_q", {}),
                                         ("qlearn", {"seed_compat": True})])
@pytest.mark.slow
def test_carried_table_rows_change_nothing(agent, extra):
    """The trainer carries each env's table rows at its state from one step to the next (patched where the
    update hit them) instead of reading the table again: the rows always equal the table's, and the carry is
    bit for bit the one of reading the table every time, on both reset paths."""
    import jax

    from jaxrobo.training.trainer import Trainer

    spec = resolve("CartPoleStayUp-v0", overrides={**TINY, "n_envs": 12, "backend": "analytic", **extra},
                   agent=agent)
    ap, ep = spec.agent_params, spec.env.default_params
    for capacity in (2, 12):
        carries = []
        for carry_rows in (True, False):
            trainer = Trainer(spec.env, spec.config)
            trainer.reset_capacity, trainer.carry_rows = capacity, carry_rows
            runner = trainer.init(jax.random.key(7), ap, ep)
            chunk = jax.jit(trainer.run_chunk)
            for _ in range(3):
                runner = chunk(runner, ap, ep)
                if carry_rows:
                    q = np.asarray(runner.agent.q)
                    expected = q[np.arange(12), :, np.asarray(runner.s), :]
                    np.testing.assert_array_equal(np.asarray(runner.q_rows), expected)
            assert (runner.q_rows is None) != carry_rows
            carries.append(jax.tree.leaves(jax.tree.map(
                lambda x: jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x,
                runner.replace(q_rows=None))))
        assert np.asarray(runner.agent.q).any()  # the tables learnt something
        for a, b in zip(*carries):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_host_loop_checkpoints_every_n_chunks_and_stops_when_asked():
    """``checkpoint`` sees the carry every ``checkpoint_every`` chunks and after the last one; ``should_stop``
    is asked before each chunk, and a stop saves the carry and returns the episodes so far, unevaluated."""
    spec = resolve("CartPoleStayUp-v0", overrides={**TINY, "chunk_steps": 10, "backend": "analytic",
                                                   "eval_episodes": 2, "eval_envs": 2})
    saved = []
    full = train(spec.env, spec.config, spec.agent_params, checkpoint_every=2,
                 checkpoint=lambda runner, chunks: saved.append((chunks, int(runner.episode.min()))))
    assert full.complete and full.chunks_done > 4 and full.eval_lengths is not None
    assert [c for c, _ in saved] == sorted({*range(2, full.chunks_done, 2), full.chunks_done})
    assert all(done < spec.config.nepisodes for _, done in saved[:-1]) and saved[-1][1] == spec.config.nepisodes
    np.testing.assert_array_equal(full.episodes_done, spec.config.nepisodes)

    asked, saved = [], []
    part = train(spec.env, spec.config, spec.agent_params, checkpoint=lambda r, c: saved.append(c),
                 should_stop=lambda: asked.append(1) or len(asked) > 3)
    assert not part.complete and part.chunks_done == 3 and saved == [3] and part.eval_lengths is None
    finished = part.episodes_done[:, None] > np.arange(spec.config.nepisodes)
    np.testing.assert_array_equal(part.lengths[finished], full.lengths[finished])
    assert np.all(part.lengths[~finished] == 0)


def test_a_trainer_handed_to_train_must_be_of_its_env_and_config():
    """train(trainer=...) runs the caller's trainer (the command's: its traces are reused); one built for another
    config or plan is refused before anything is traced."""
    from jaxrobo.training.trainer import Trainer

    spec = resolve("CartPoleStayUp-v0", overrides=dict(n_envs=4, nepisodes=2, nsteps=20))
    other = resolve("CartPoleStayUp-v0", overrides=dict(n_envs=8, nepisodes=2, nsteps=20))
    trainer = Trainer(spec.env, other.config)
    with pytest.raises(ValueError, match="built for this env and config"):
        train(spec.env, spec.config, spec.agent_params, trainer=trainer)
    trainer = Trainer(spec.env, spec.config)
    with pytest.raises(ValueError, match="built for this env and config"):
        train(spec.env, spec.config, spec.agent_params, trainer=trainer, plan=trainer.plan.replace(env_group=2))
