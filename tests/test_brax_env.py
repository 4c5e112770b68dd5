"""Brax's Env interface over jaxrobo envs (jaxrobo.interop.brax_env): jit/vmap, fresh autoresets, truncation vs
termination, the NaN guard, and Brax's own PPO and SAC trainers running unchanged on the continuous ids (tiny, CPU)."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.interop import brax_env
from jaxrobo.core.config import ConfigError

IDS = ("CartPoleContinuous-v0", "QuadcopterGotoTwist-v0")


@functools.lru_cache(maxsize=None)
def _env(env_id: str, **overrides) -> brax_env.BraxEnv:
    return brax_env.make(env_id, **overrides)


@functools.lru_cache(maxsize=None)
def _wrapped(env_id: str, episode_length: int, action_repeat: int = 1, **overrides):
    w = brax_env.wrap_for_training(_env(env_id, **overrides), episode_length=episode_length,
                                   action_repeat=action_repeat)
    return w, jax.jit(w.reset), jax.jit(w.step)


def _keys(n: int, seed: int = 0) -> jax.Array:
    return jax.random.split(jax.random.PRNGKey(seed), n)  # Brax's raw uint32 keys


@pytest.mark.parametrize("env_id", IDS)
def test_jit_vmap_shapes(env_id):
    env = _env(env_id)
    assert env.backend in ("analytic", "rigid")
    n, obs, act = 3, env.observation_size, env.action_size
    assert (obs, act) == {"CartPoleContinuous-v0": (4, 1), "QuadcopterGotoTwist-v0": (7, 4)}[env_id]
    state = jax.jit(jax.vmap(env.reset))(_keys(n))
    assert state.obs.shape == (n, obs) and state.obs.dtype == jnp.float32
    assert state.reward.shape == state.done.shape == state.info["truncation"].shape == (n,)
    actions = jnp.linspace(-1.0, 1.0, n * act, dtype=jnp.float32).reshape(n, act)
    nxt = jax.jit(jax.vmap(env.step))(state, actions)
    assert nxt.obs.shape == (n, obs) and nxt.reward.dtype == jnp.float32 and nxt.done.dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(nxt.obs))) and not np.array_equal(nxt.obs, state.obs)
    assert set(brax_env.BASE_METRICS) <= set(nxt.metrics) and np.all(nxt.pipeline_state.steps == 1)
    # A typed key works too, and the same key gives the same state.
    a, b = env.reset(jax.random.key(3)), env.reset(jax.random.wrap_key_data(jax.random.PRNGKey(3)))
    np.testing.assert_array_equal(a.obs, b.obs)


def test_autoreset_draws_fresh_randomness_not_a_cached_first_state():
    """Two episodes in one env start from different states (Brax's AutoResetWrapper would repeat the first)."""
    w, reset, step = _wrapped("QuadcopterGotoTwist-v0", 3)
    state = reset(_keys(2))
    first = np.asarray(state.obs)
    hover = jnp.zeros((2, 4))
    for _ in range(3):
        state = step(state, hover)
    assert np.all(np.asarray(state.done) == 1) and np.all(np.asarray(state.info["truncation"]) == 1)
    second = np.asarray(state.obs)  # the next episodes' first observations
    assert np.all(np.abs(second - first).max(axis=1) > 1e-3), (first, second)
    np.testing.assert_array_equal(np.asarray(state.pipeline_state.steps), 0)
    # The step after a reset continues the new episode, not the old one.
    state = step(state, hover)
    assert np.all(np.asarray(state.done) == 0) and np.all(np.asarray(state.info["steps"]) == 1)


def test_brax_default_wrapper_is_not_used_because_it_replays_the_first_state():
    """Why ppo.train must get wrap_env_fn=wrap_for_training: Brax's own wrap (wrap_env_fn=None) auto-resets every
    episode to the cached first state, so every episode after the first starts identically."""
    from brax.envs.wrappers import training as brax_training

    env = _env("QuadcopterGotoTwist-v0")
    w = brax_training.wrap(env, episode_length=3, action_repeat=1)
    state = jax.jit(w.reset)(_keys(2))
    first = np.asarray(state.obs)
    step = jax.jit(w.step)
    for _ in range(3):
        state = step(state, jnp.zeros((2, 4)))
    assert np.all(np.asarray(state.done) == 1)
    np.testing.assert_array_equal(np.asarray(state.obs), first)  # the same episode again: no fresh randomness


def test_truncation_on_time_limit_only():
    _, reset, step = _wrapped("CartPoleContinuous-v0", 4, init_noise=0.0)
    state = reset(_keys(2))
    for t in range(4):
        state = step(state, jnp.zeros((2, 1)))
        expected = float(t == 3)
        np.testing.assert_array_equal(state.done, expected)
        np.testing.assert_array_equal(state.info["truncation"], expected)
    np.testing.assert_array_equal(state.metrics["truncated"], 1.0)
    np.testing.assert_array_equal(state.metrics["terminated"], 0.0)
    np.testing.assert_array_equal(state.info["episode_metrics"]["length"], 4.0)
    np.testing.assert_array_equal(state.info["episode_metrics"]["sum_reward"], 4.0)


def test_termination_is_not_truncation():
    """The pole starts past its limit's edge: the first step terminates, without truncation (it bootstraps as a
    true end); Brax's trainers see done=1, truncation=0."""
    _, reset, step = _wrapped("CartPoleContinuous-v0", 50, init_noise=0.0, init_pole_angle=0.69)
    state = step(reset(_keys(2)), -jnp.ones((2, 1)))  # the cart moves away from under the pole
    np.testing.assert_array_equal(state.done, 1.0)
    np.testing.assert_array_equal(state.info["truncation"], 0.0)
    np.testing.assert_array_equal(state.metrics["terminated"], 1.0)
    assert np.all(np.abs(np.asarray(state.obs)[:, 2] - 0.69) < 1e-5)  # the next episode's first observation


def test_nan_guard_ends_the_episode():
    env = _env("CartPoleContinuous-v0")
    nxt = jax.jit(env.step)(env.reset(jax.random.PRNGKey(0)), jnp.array([jnp.nan]))
    assert float(nxt.done) == 1.0 and float(nxt.metrics["physics_nan"]) == 1.0
    assert float(nxt.info["truncation"]) == 0.0 and float(nxt.reward) == 0.0
    assert bool(jnp.all(jnp.isfinite(nxt.obs)))
    # Through the training wrapper the episode ends and the next one starts finite.
    _, reset, step = _wrapped("CartPoleContinuous-v0", 50)
    state = step(reset(_keys(2)), jnp.array([[jnp.nan], [0.0]]))
    np.testing.assert_array_equal(state.done, [1.0, 0.0])
    np.testing.assert_array_equal(state.metrics["physics_nan"], [1.0, 0.0])
    assert bool(jnp.all(jnp.isfinite(state.obs)))


def test_action_repeat_counts_env_steps_and_stops_at_done():
    _, reset, step = _wrapped("CartPoleContinuous-v0", 5, action_repeat=2, init_noise=0.0)
    state = reset(_keys(1))
    steps = []
    for _ in range(3):
        state = step(state, jnp.zeros((1, 1)))
        steps.append(int(state.info["steps"][0]))
    assert steps == [2, 4, 5]  # the third call stops at the limit (step 5), not at 6
    assert float(state.info["truncation"][0]) == 1.0 and float(state.reward[0]) == 1.0


def test_discrete_ids_are_refused_naming_the_continuous_id():
    with pytest.raises(ConfigError, match="Discrete.*'CartPoleContinuous-v0'"):
        brax_env.make("CartPoleStayUp-v0", backend="analytic")
    with pytest.raises(ConfigError, match="Discrete.*'QuadcopterGotoTwist-v0'"):
        brax_env.make("QuadcopterGoto-v1")


def test_wrapper_arguments_are_validated():
    env = _env("CartPoleContinuous-v0")
    with pytest.raises(ConfigError, match="episode_length=0"):
        brax_env.wrap_for_training(env, episode_length=0)
    with pytest.raises(ConfigError, match="action_repeat"):
        brax_env.wrap_for_training(env, episode_length=10, action_repeat=1.5)
    with pytest.raises(ConfigError, match="randomization_fn"):
        brax_env.wrap_for_training(env, episode_length=10, randomization_fn=lambda sys: (sys, None))


def _small_ppo_networks():
    from brax.training.agents.ppo import networks as ppo_networks

    return functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(8,),
                             value_hidden_layer_sizes=(8,))


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["QuadcopterGotoTwist-v0"])  # the cart-pole and SAC: tests/test_deep.py (CLI)
def test_brax_ppo_trains_on_continuous_id(env_id):
    from brax.training.agents.ppo import train as ppo

    progress, wrapped = [], []

    def wrap(env, **kwargs):  # Brax's trainer must build its train and eval envs through jaxrobo's wrapper
        wrapped.append(kwargs)
        return brax_env.wrap_for_training(env, **kwargs)

    make_policy, params, metrics = ppo.train(
        _env(env_id), num_timesteps=640, episode_length=20, wrap_env_fn=wrap,
        num_envs=4, batch_size=4, num_minibatches=2, unroll_length=5, num_updates_per_batch=1,
        num_evals=2, num_eval_envs=2, network_factory=_small_ppo_networks(), seed=0,
        progress_fn=lambda step, m: progress.append((step, m)))
    assert len(progress) == 2 and progress[-1][0] >= 640
    assert [(k["episode_length"], k["action_repeat"]) for k in wrapped] == [(20, 1), (20, 1)]  # train, eval
    assert np.isfinite(metrics["eval/episode_reward"])
    assert 0 < metrics["eval/avg_episode_length"] <= 20
    policy = make_policy(params, deterministic=True)
    env = _env(env_id)
    action, _ = policy(env.reset(jax.random.PRNGKey(1)).obs[None], jax.random.PRNGKey(2))
    assert action.shape == (1, env.action_size) and bool(jnp.all(jnp.abs(action) <= 1.0))
    if env_id == "QuadcopterGotoTwist-v0":
        assert 0.0 <= metrics["eval/episode_arrived"] <= 1.0


def test_playground_training_wrapper_drives_a_brax_env():
    """MuJoCo Playground's own training wrapper drives a BraxEnv. Its default replays a cached first state (like
    Brax's); full_reset=True draws fresh episodes but also resets info on the done step, so the time-limit step
    loses info['truncation'] there: jaxrobo's wrap_for_training keeps both."""
    wrapper = pytest.importorskip("mujoco_playground._src.wrapper",
                                  reason="MuJoCo Playground is not installed (pip install jaxrobo[playground])")
    env = _env("QuadcopterGotoTwist-v0")
    hover = jnp.zeros((2, 4))
    out = {}
    for full_reset in (True, False):
        w = wrapper.wrap_for_brax_training(env, episode_length=3, action_repeat=1, full_reset=full_reset)
        state = jax.jit(w.reset)(_keys(2))
        first = np.asarray(state.obs)
        step = jax.jit(w.step)
        for _ in range(3):
            state = step(state, hover)
        np.testing.assert_array_equal(state.done, 1.0)
        out[full_reset] = (first, np.asarray(state.obs), np.asarray(state.info["truncation"]))
    first, nxt, truncation = out[False]
    np.testing.assert_array_equal(nxt, first)  # cached first state
    np.testing.assert_array_equal(truncation, 1.0)
    first, nxt, truncation = out[True]
    assert np.all(np.abs(nxt - first).max(axis=1) > 1e-3)  # fresh episodes
    np.testing.assert_array_equal(truncation, 0.0)  # Playground's full reset wiped the flag with the info
    # jaxrobo's wrapper: fresh episodes and the flag (test_autoreset_draws_fresh_randomness_not_a_cached_first_state).


def _closed_loop(env, policy, n: int, steps: int):
    """``n`` episodes of a jaxrobo env under ``policy(obs)``, each frozen at its first done step."""
    def one(key):
        def body(s, _):
            nxt = env.step(s, policy(s.obs))
            return jax.tree.map(lambda new, old: jnp.where(s.done, old, new), nxt, s), None

        return jax.lax.scan(body, env.reset(key), None, steps)[0]

    return jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(0), n))


def test_continuous_cartpole_is_balanced_by_linear_feedback_inside_the_box():
    """The action Box is wide enough: pushing the cart towards the side the pole leans (a linear feedback,
    clipped to [-1, 1]) keeps the pole up for the whole 1000-step episode."""
    import jaxrobo

    env = jaxrobo.make("CartPoleContinuous-v0")
    s = _closed_loop(env, lambda o: jnp.clip(2.0 * o[2] + 0.5 * o[3] + 0.1 * o[0] + 0.2 * o[1], -1, 1)[None], 3,
                     1000)
    np.testing.assert_array_equal(s.steps, 1000)
    np.testing.assert_array_equal(s.truncated, True)


def test_twist_reaches_goals_without_the_obstacle_and_the_obstacle_is_in_the_way():
    """The Twist's axes and signs: turning towards the bearing (+ = left) while flying forward and climbing to the
    goal altitude arrives every time without an obstacle; with the default obstacle between start and goal the
    same straight-line flight crashes into it (the task needs avoiding, as in QuadcopterGoto-v1)."""
    import jaxrobo

    def straight(o):
        dist, bearing, dz = o[0], o[1], o[2]
        forward = 2.0 * dist * jnp.cos(bearing) * (jnp.abs(bearing) < 0.6)
        return jnp.clip(jnp.stack([forward, 0.0, 2.0 * dz, 3.0 * bearing]), -1.0, 1.0)

    free = _closed_loop(jaxrobo.make("QuadcopterGotoTwist-v0", n_obstacles=0), straight, 8, 100)
    assert bool(jnp.all(free.task.arrived)) and not bool(jnp.any(free.task.crashed))
    blocked = _closed_loop(jaxrobo.make("QuadcopterGotoTwist-v0"), straight, 8, 100)
    assert bool(jnp.all(blocked.task.crashed)) and not bool(jnp.any(blocked.task.arrived))


@pytest.mark.parametrize("env_id", ["CartPoleStayUp-v0", "ArmReach-v0"])
def test_a_discrete_id_takes_the_argmax_of_braxs_outputs(env_id):
    """discrete="argmax": every id is a Brax Env; the env steps with the index of the largest output."""
    kw = {"backend": "analytic"} if env_id.startswith("CartPole") else {}
    benv = brax_env.make(env_id, discrete="argmax", **kw)
    n = benv.env.num_actions
    assert benv.action_size == n
    np.testing.assert_array_equal(benv.scale_action(jnp.eye(n)), np.arange(n))
    state = jax.jit(benv.reset)(jax.random.PRNGKey(0))
    direct = benv.env.step(state.pipeline_state, jnp.int32(n - 1), benv.params)
    stepped = jax.jit(benv.step)(state, jnp.eye(n)[n - 1])
    np.testing.assert_array_equal(stepped.obs, direct.obs)
    batch = jax.jit(jax.vmap(benv.reset))(jax.random.split(jax.random.PRNGKey(1), 3))
    assert batch.obs.shape == (3, benv.observation_size)
    with pytest.raises(ConfigError, match="discrete='argmax'"):
        brax_env.make(env_id, **kw)
    with pytest.raises(ConfigError, match="discrete='nearest'"):
        brax_env.make(env_id, discrete="nearest", **kw)


def test_brax_ppo_trains_on_a_discrete_id_through_argmax():
    from brax.training.agents.ppo import train as ppo

    env = brax_env.make("CartPoleStayUp-v0", discrete="argmax", backend="analytic")
    make_policy, params, metrics = ppo.train(
        env, num_timesteps=320, episode_length=20, wrap_env_fn=brax_env.wrap_for_training,
        num_envs=4, batch_size=4, num_minibatches=2, unroll_length=5, num_updates_per_batch=1,
        num_evals=2, num_eval_envs=2, network_factory=_small_ppo_networks(), seed=0)
    assert np.isfinite(metrics["eval/episode_reward"]) and 0 < metrics["eval/avg_episode_length"] <= 20
