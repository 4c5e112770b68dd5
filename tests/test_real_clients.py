"""Real clients run unchanged (tiny sizes, CPU): Brax's default ``ppo.train(environment=env)`` through its
evaluation (Brax's own ``training.wrap`` and ``EvalWrapper``, which adds a ``reward`` metric), MuJoCo Playground's
training wrapper inside ``ppo.train``, and the Gymnasium envs through stdlib ``pickle`` and a ``multiprocessing``
pool (what SB3's ``SubprocVecEnv`` and user pools do). SB3 itself needs PyTorch, which the test extra does not
carry: tests/test_sb3.py runs it where the sb3 extra is installed (CI installs it)."""
from __future__ import annotations

import functools
import multiprocessing
import pickle

import gymnasium as gym
import numpy as np
import pytest

from jaxrobo.interop import brax_env
from jaxrobo.interop.gym_adapter import JaxroboEnv, JaxroboVectorEnv

TINY_PPO = dict(num_timesteps=320, episode_length=20, num_envs=4, batch_size=4, num_minibatches=2, unroll_length=5,
                num_updates_per_batch=1, num_evals=2, num_eval_envs=2, seed=0)


def _small_networks():
    from brax.training.agents.ppo import networks as ppo_networks

    return functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(8,),
                             value_hidden_layer_sizes=(8,))


def _ppo(env, **kwargs):
    from brax.training.agents.ppo import train as ppo

    progress = []
    _, params, metrics = ppo.train(environment=env, network_factory=_small_networks(),
                                   progress_fn=lambda step, m: progress.append((step, m)), **TINY_PPO, **kwargs)
    return progress, metrics


def test_braxs_default_ppo_train_runs_through_its_evaluations():
    """``wrap_env_fn`` left out: Brax wraps the env itself (EpisodeWrapper, AutoResetWrapper, EvalWrapper adding
    ``metrics['reward']``); every evaluation runs and reports."""
    progress, metrics = _ppo(brax_env.make("CartPoleContinuous-v0"))
    assert len(progress) == TINY_PPO["num_evals"]
    assert np.isfinite(metrics["eval/episode_reward"]) and 0 < metrics["eval/avg_episode_length"] <= 20
    assert "eval/episode_terminated" in metrics  # jaxrobo's own metrics reach Brax's evaluator too


def test_brax_env_step_keeps_metrics_a_wrapper_added():
    import jax

    env = brax_env.make("CartPoleContinuous-v0")
    state = env.reset(jax.random.PRNGKey(0))
    state.metrics["reward"] = state.reward  # what Brax's EvalWrapper does
    nxt = env.step(state, np.zeros(env.action_size, np.float32))
    assert set(nxt.metrics) == set(state.metrics)
    assert float(nxt.metrics["reward"]) == float(state.reward)  # the wrapper updates its own key, not jaxrobo


def test_playground_wrapper_inside_ppo_train():
    wrapper = pytest.importorskip("mujoco_playground._src.wrapper",
                                  reason="MuJoCo Playground is not installed (pip install jaxrobo[playground])")
    progress, metrics = _ppo(brax_env.make("CartPoleContinuous-v0"), wrap_env_fn=wrapper.wrap_for_brax_training)
    assert len(progress) == TINY_PPO["num_evals"] and np.isfinite(metrics["eval/episode_reward"])


# ---- stdlib pickle and multiprocessing ---------------------------------------------------------------------------
@pytest.mark.parametrize("make", [
    lambda: JaxroboEnv("CartPoleStayUp-v0", control_type="position"),
    lambda: gym.make("jaxrobo/CartPoleStayUp-v0"),
    lambda: gym.make("jaxrobo/CartPoleStayUp-v0", engine="numpy", backend="analytic"),
    lambda: JaxroboVectorEnv("CartPoleStayUp-v0", num_envs=3),
], ids=["JaxroboEnv", "gym.make", "gym.make engine=numpy", "JaxroboVectorEnv"])
def test_a_pickled_env_goes_on_where_the_original_is(make):
    env = make()
    vector = isinstance(env, gym.vector.VectorEnv)
    action = np.ones(env.num_envs, np.int64) if vector else 1
    env.reset(seed=5)
    env.step(action)
    copy = pickle.loads(pickle.dumps(env))
    for _ in range(3):
        a, b = env.step(action), copy.step(action)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    fresh = pickle.loads(pickle.dumps(make()))  # never reset: the copy is as usable
    obs, _ = fresh.reset(seed=5)
    np.testing.assert_array_equal(obs, make().reset(seed=5)[0])


def _rollout(env) -> list[float]:
    obs, _ = env.reset(seed=7)
    out = [float(np.asarray(obs).sum())]
    for _ in range(5):
        obs, *_ = env.step(0)
        out.append(float(np.asarray(obs).sum()))
    return out


def test_an_env_passes_through_a_spawned_multiprocessing_pool():
    env = JaxroboEnv("CartPoleStayUp-v0")
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        (remote,) = pool.map(_rollout, [env])
    assert remote == _rollout(env)
