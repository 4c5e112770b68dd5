"""CartPoleStayUp follows the seed's task (docs/cartpole.md): actions, termination, reward, reset pose, time limit,
NaN guard, jit/vmap."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from envs.cartpole.stay_up import ACTION_STEPS
from jaxrobo.core.config import ConfigError
from jaxrobo.task.wrappers import AutoReset


def test_registered_ids_and_action_counts():
    assert {"CartPoleStayUp-v0", "CartPoleStayUpLeftRight-v0"} <= set(jaxrobo.registered())
    assert jaxrobo.make("CartPoleStayUp-v0").num_actions == 4
    assert jaxrobo.make("CartPoleStayUpLeftRight-v0").num_actions == 2
    assert jaxrobo.spec("CartPoleStayUp-v0").max_episode_steps == 1000


def test_seed_defaults_from_yaml(cartpole):
    env, _, _ = cartpole
    p = env.default_params
    assert (p.pos_step, p.max_base_pose_x, p.min_base_pose_x, p.max_pole_angle, p.max_base_velocity) == (
        0.016, 2.5, -2.5, 0.7, 50.0)
    assert env.options.running_step == 0.04 and env.options.control_type == "velocity"
    assert env.robot.sim.n_substeps == 4


@pytest.mark.parametrize("action", range(4))
def test_each_action_adds_its_step_to_the_command(cartpole, action):
    env, reset, step = cartpole
    state = step(reset(jax.random.key(0)), action)
    assert float(state.task.command) == pytest.approx(ACTION_STEPS[action] * 0.016)
    state = step(state, action)
    assert float(state.task.command) == pytest.approx(2 * ACTION_STEPS[action] * 0.016)


def test_reward_is_one_every_step_including_the_falling_one(cartpole):
    env, reset, step = cartpole
    state = reset(jax.random.key(1))
    rewards, done = [], False
    for _ in range(300):
        state = step(state, 2)  # keep pushing left: the episode must end
        rewards.append(float(state.reward))
        if bool(state.terminated):
            done = True
            break
    assert done and all(r == 1.0 for r in rewards)
    assert not bool(state.truncated)


def test_termination_limits_are_inclusive(cartpole):
    env, _, _ = cartpole
    p = env.default_params
    done = lambda obs: bool(env._is_done(jnp.asarray(obs, jnp.float32), None, None, p))  # noqa: E731
    assert done([2.5, 0, 0, 0]) and done([-2.5, 0, 0, 0])
    assert done([0, 0, 0.7, 0]) and done([0, 0, -0.7, 0])
    assert not done([2.49, 0, 0.69, 0]) and not done([-2.49, 0, -0.69, 0])


def test_initial_pose_is_a_parameter_pole_at_30_degrees():
    env = jaxrobo.make("CartPoleStayUp-v0", init_pole_angle=float(np.deg2rad(30)), init_noise=0.0, init_pos=0.5,
                       max_pole_angle=1.0)
    state = env.reset(jax.random.key(0))
    np.testing.assert_allclose(np.asarray(state.obs), [0.5, 0.0, np.deg2rad(30), 0.0], atol=1e-6)


def test_reset_noise_gives_different_starts_per_key(cartpole):
    _, reset, _ = cartpole
    a, b = reset(jax.random.key(0)).obs, reset(jax.random.key(1)).obs
    assert not np.allclose(a, b) and np.all(np.abs(np.asarray(a)) <= 0.05 + 1e-6)


def test_truncation_is_distinct_from_termination():
    env = jaxrobo.make("CartPoleStayUp-v0", max_episode_steps=3, init_noise=0.0)
    state = env.reset(jax.random.key(0))
    step = jax.jit(env.step)
    for _ in range(3):
        state = step(state, 0)
    assert bool(state.truncated) and not bool(state.terminated)


def test_round_obs_mode_rounds_to_one_decimal():
    env = jaxrobo.make("CartPoleStayUp-v0", round_obs=True)
    obs = np.asarray(env.step(env.reset(jax.random.key(3)), 3).obs)
    np.testing.assert_allclose(obs, np.round(obs, 1), atol=1e-6)


def test_non_finite_physics_ends_the_episode_and_never_leaks(cartpole):
    env, reset, step = cartpole
    state = reset(jax.random.key(0))
    bad = state.replace(pipeline_state=state.pipeline_state.replace(qvel=jnp.array([jnp.nan, 0.0])))
    out = step(bad, 1)
    assert bool(out.physics_nan) and bool(out.terminated) and float(out.reward) == 0.0
    assert np.all(np.isfinite(np.asarray(out.obs)))


def test_reset_and_step_vmap_and_jit_over_envs_and_params(cartpole):
    env, _, _ = cartpole
    keys = jax.random.split(jax.random.key(0), 8)
    params = jax.tree.map(lambda x: jnp.broadcast_to(x, (8,)), env.default_params)
    params = params.replace(pos_step=jnp.linspace(0.01, 0.08, 8))
    states = jax.jit(jax.vmap(env.reset))(keys, params)
    states = jax.jit(jax.vmap(env.step))(states, jnp.full(8, 3), params)
    np.testing.assert_allclose(np.asarray(states.task.command), 10 * np.linspace(0.01, 0.08, 8), rtol=1e-5)


def test_autoreset_draws_fresh_random_starts():
    env = AutoReset(jaxrobo.make("CartPoleStayUp-v0", max_episode_steps=2))
    step = jax.jit(env.step)
    state = env.reset(jax.random.key(0))
    starts = []
    for _ in range(6):
        state = step(state, 0)
        if bool(state.done):
            starts.append(np.asarray(state.obs))
            assert not np.allclose(state.info["final_obs"], state.obs)
    assert len(starts) == 3
    assert not np.allclose(starts[0], starts[1]) and not np.allclose(starts[1], starts[2])


@pytest.mark.parametrize("overrides,fragment", [
    ({"control_type": "torque"}, "control_type='torque': allowed values are 'velocity', 'position', 'effort'"),
    ({"pos_stp": 0.1}, "unknown key 'pos_stp' (did you mean pos_step"),
    ({"pos_step": -1.0}, "pos_step=-1.0: expected a number > 0.0"),
    ({"n_actions": 3}, "n_actions=3: allowed values are 2, 4"),
    ({"running_step": 0.045}, "not a whole multiple"),
    ({"max_episode_steps": "long"}, "max_episode_steps='long': expected an integer"),
])
def test_bad_overrides_raise_clear_errors(overrides, fragment):
    with pytest.raises(ConfigError) as err:
        jaxrobo.make("CartPoleStayUp-v0", **overrides)
    assert fragment in str(err.value)


def test_unknown_env_id_suggests_close_match():
    with pytest.raises(ConfigError, match="CartPoleStayUp-v0"):
        jaxrobo.make("CartPoleStayUp-v9")
