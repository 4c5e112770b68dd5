"""Tests of the custom task; copy and extend them with your task. Run from this folder:
``JAX_PLATFORMS=cpu python -m pytest test_my_task.py -q``."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxrobo
import my_task  # noqa: F401  (registers MyPendulum-v0)


def test_env_card_holds():
    env = jaxrobo.make("MyPendulum-v0", init_noise=0.0)
    assert env.num_actions == 3 and env.observation_size == 2 and env.spec.max_episode_steps == 200
    step = jax.jit(env.step)
    state = env.reset(jax.random.key(0))
    np.testing.assert_allclose(np.asarray(state.obs), 0.0, atol=1e-6)  # upright and still at reset
    # From upright, full torque towards +x tips the rod over +max_angle: reward 1 on every step, then done.
    steps = 0
    while not bool(state.done):
        state = step(state, 2)
        steps += 1
        assert float(state.reward) == 1.0 and steps < 200
    assert float(state.obs[0]) >= float(env.default_params.max_angle)


def test_torque_pushes_the_right_way():
    env = jaxrobo.make("MyPendulum-v0", init_noise=0.0, init_angle=0.2)
    step = jax.jit(env.step)
    left = step(env.reset(jax.random.key(0)), 0)
    right = step(env.reset(jax.random.key(0)), 2)
    assert float(right.obs[1]) > float(left.obs[1])  # +torque speeds the rod towards +x
    assert jnp.all(jnp.isfinite(right.obs))
