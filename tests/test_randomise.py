"""Domain randomisation (jaxrobo.task.randomise): ranges validated at the boundary, drawn per episode at reset, the
same physics on every backend that offers it, nothing traced when off, the kernels kept when on."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from jaxrobo.core.config import ConfigError
from jaxrobo.task import randomise

GOTO = "QuadcopterGoto-v2"


def _roll(env, n_envs=3, steps=12, action=3, params=None, seed=0):
    params = env.default_params if params is None else params
    s = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(seed), n_envs), params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, None)))
    out = [s]
    for _ in range(steps):
        s = step(s, jnp.full(n_envs, action, jnp.int32), params)
        out.append(s)
    return out


@pytest.mark.parametrize("value, message", [
    ([1.2, 0.8], "low 1.2 > high 0.8"),
    ([0.1, 1.0], "outside the physical limits"),
    ([1.0], "expected a range [low, high]"),
    (1.0, "expected a range [low, high]"),
    ([1.0, "x"], "expected a range [low, high]"),
    ([1.0, float("inf")], "expected a range [low, high]"),
])
def test_a_bad_range_is_refused_naming_the_field(value, message):
    with pytest.raises(ConfigError, match="rand_mass") as err:
        jaxrobo.make(GOTO, randomise=True, rand_mass=value)
    assert message in str(err.value)


def test_a_range_without_randomise_and_an_unsupported_backend_are_refused():
    with pytest.raises(ConfigError, match="rand_wind.*randomise is false"):
        jaxrobo.make(GOTO, rand_wind=[0.0, 1.0])
    with pytest.raises(ConfigError, match="backend='generalized' cannot randomise rand_cart_mass"):
        jaxrobo.make("CartPoleStayUp-v0", backend="generalized", randomise=True)
    with pytest.raises(ConfigError, match="declares no randomisation ranges"):
        jaxrobo.make("QuadcopterLiveShow-v0", randomise=True)
    with pytest.raises(ConfigError, match="rand_mass.*randomise is false"):  # pinned away from nominal: also read
        jaxrobo.make(GOTO, rand_mass=[1.5, 1.5])
    jaxrobo.make(GOTO, rand_mass=[1.0, 1.0])  # the default, as a saved run's config.yaml lists it


def test_off_traces_nothing_and_keeps_the_state_as_it_was():
    env = jaxrobo.make(GOTO)
    state = env.reset(jax.random.key(0))
    assert state.domain == () and not env.randomised
    assert env.step_kernel is not None and env.robot.advance_kernel is not None


def test_pinned_nominal_physics_equal_randomisation_off():
    """randomise=true with every range at its nominal value flies the same flights as randomise=false."""
    for env_id, kw in [(GOTO, {}), ("CartPoleStayUp-v0", {"backend": "analytic"})]:
        off = _roll(jaxrobo.make(env_id, **kw), action=1)
        on = _roll(jaxrobo.make(env_id, randomise=True, **kw), action=1)
        for a, b in zip(off, on):
            np.testing.assert_allclose(np.asarray(b.obs), np.asarray(a.obs), rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(np.asarray(b.reward), np.asarray(a.reward))


def test_each_reset_draws_within_the_ranges_and_an_episode_keeps_its_draw():
    env = jaxrobo.make(GOTO, randomise=True, rand_mass=[0.8, 1.2], rand_wind=[0.5, 1.0])
    states = _roll(env, n_envs=16, steps=3)
    d0 = states[0].domain
    m, w = np.asarray(d0["mass"]), np.asarray(d0["wind"])
    assert ((m >= 0.8) & (m <= 1.2)).all() and ((w >= 0.5) & (w <= 1.0)).all() and len(set(m.tolist())) == 16
    np.testing.assert_array_equal(np.asarray(states[-1].domain["mass"]), m)
    other = jax.vmap(env.reset)(jax.random.split(jax.random.key(1), 16)).domain["mass"]
    assert not np.allclose(np.asarray(other), m)
    # the reset's other draws (start heading, goal, obstacle) are those of the un-randomised task
    plain = jax.vmap(jaxrobo.make(GOTO).reset)(jax.random.split(jax.random.key(0), 16))
    np.testing.assert_array_equal(np.asarray(states[0].task.goal), np.asarray(plain.task.goal))


@pytest.mark.slow  # the rigid body against MJX is held unrandomised in the default tier (test_quadcopter)
def test_the_rigid_body_and_mjx_fly_the_same_randomised_drone():
    kw = dict(randomise=True, rand_mass=[0.7, 1.4], rand_motor_gain=[0.8, 1.2], rand_wind=[0.5, 1.5])
    rigid = _roll(jaxrobo.make(GOTO, backend="rigid", **kw), steps=6, action=0)
    mjx = _roll(jaxrobo.make(GOTO, backend="mjx", **kw), steps=6, action=0)
    for a, b in zip(rigid, mjx):
        np.testing.assert_allclose(np.asarray(b.pipeline_state.qpos), np.asarray(a.pipeline_state.qpos), atol=2e-4)


def test_the_closed_form_and_mjx_swing_the_same_randomised_cartpole():
    kw = dict(randomise=True, rand_cart_mass=[0.5, 2.0], rand_pole_mass=[0.5, 2.0], rand_pole_length=[0.5, 2.0])
    analytic = _roll(jaxrobo.make("CartPoleStayUp-v0", backend="analytic", **kw), steps=20, action=1)
    mjx = _roll(jaxrobo.make("CartPoleStayUp-v0", backend="mjx", **kw), steps=20, action=1)
    np.testing.assert_allclose(np.asarray(mjx[-1].obs), np.asarray(analytic[-1].obs), atol=1e-4)
    # and the draws matter: a longer pole falls slower than the nominal one
    nominal = _roll(jaxrobo.make("CartPoleStayUp-v0", backend="analytic"), steps=20, action=1)
    assert not np.allclose(np.asarray(analytic[-1].obs), np.asarray(nominal[-1].obs), atol=1e-3)


def test_wind_pushes_the_drone_along_its_direction_and_a_heavier_drone_sinks():
    env = jaxrobo.make(GOTO, randomise=True, rand_wind=[1.0, 1.0])
    states = _roll(env, n_envs=4, steps=4, action=3)  # climb: no horizontal command
    d = states[0].domain
    heading = np.stack([np.cos(d["wind_heading"]), np.sin(d["wind_heading"])], 1)
    drift = np.asarray(states[-1].pipeline_state.qpos[:, :2])
    assert (np.sum(drift * heading, 1) > 0.05).all()
    heavy = jaxrobo.make(GOTO, randomise=True, rand_mass=[2.0, 2.0])
    z_heavy = np.asarray(_roll(heavy, steps=3, action=1)[-1].pipeline_state.qpos[:, 2])
    z_nominal = np.asarray(_roll(jaxrobo.make(GOTO), steps=3, action=1)[-1].pipeline_state.qpos[:, 2])
    assert (z_heavy < z_nominal - 0.05).all()


def test_observation_noise_reaches_the_agent_only():
    noisy_env = jaxrobo.make(GOTO, randomise=True, rand_obs_noise=[0.1, 0.1])
    noisy, clean = _roll(noisy_env, steps=4, action=1), _roll(jaxrobo.make(GOTO), steps=4, action=1)
    for a, b in zip(clean, noisy):
        np.testing.assert_array_equal(np.asarray(b.reward), np.asarray(a.reward))
        diff = np.asarray(b.obs) - np.asarray(a.obs)
        assert 0.02 < np.abs(diff).mean() < 0.3
    assert not np.allclose(np.asarray(noisy[1].obs - clean[1].obs), np.asarray(noisy[2].obs - clean[2].obs))


def test_randomised_runs_keep_their_kernels():
    """The kernels take each env's draw as per-env inputs (tests/test_randomise_kernels.py holds them to the XLA
    path); only the quadcopter off ``rigid`` and the cart-pole off ``analytic`` have none, as without randomisation."""
    from jaxrobo.speed import plan
    from jaxrobo.training.trainer import TrainConfig

    goto = jaxrobo.make(GOTO, randomise=True)
    assert goto.step_kernel is not None and goto.step_kernel_refusal is None
    assert plan.physics_kernel(goto) and plan.task_kernel(goto)
    cart = jaxrobo.make("CartPoleStayUp-v0", backend="analytic", randomise=True)
    assert plan.chunk_kernel_refusal(cart, TrainConfig()) is None
    assert plan.default_fused(cart, "gpu", config=TrainConfig(n_envs=16384)) == "pallas"
    mjx = jaxrobo.make("CartPoleStayUp-v0", backend="mjx", randomise=True)
    assert "backend='mjx'" in plan.chunk_kernel_refusal(mjx, TrainConfig())


def test_the_ranges_are_traced_so_a_vmap_can_vary_them():
    env = jaxrobo.make(GOTO, randomise=True)
    rows = [env.default_params.replace(rand_mass=(v, v)) for v in (0.5, 1.0, 2.0)]
    stacked = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *rows)
    drawn = jax.vmap(lambda p: env.reset(jax.random.key(0), p).domain["mass"])(stacked)
    np.testing.assert_array_equal(np.asarray(drawn), [0.5, 1.0, 2.0])
    pinned = randomise.pinned(env.default_params, {"mass": 1.3})
    assert pinned.rand_mass == (1.3, 1.3)
    with pytest.raises(ValueError, match="not a randomisation range"):
        randomise.pinned(env.default_params, {"gravity": 1.0})


def test_a_sweep_refuses_ranges_without_randomise_and_parses_range_values():
    from jaxrobo.training.sweep.planning import parse_grid, plan_sweep

    assert parse_grid(["rand_mass=[1,1],[0.8,1.2]"]) == {"rand_mass": [[1, 1], [0.8, 1.2]]}
    with pytest.raises(ConfigError, match="rand_mass.*randomise=false"):
        plan_sweep(GOTO, [{"rand_mass": [0.8, 1.2]}], overrides={"n_envs": 2, "nepisodes": 2})
