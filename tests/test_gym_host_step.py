"""``JaxroboEnv(..., engine="numpy")``: the cart-pole and the Goto tasks stepped on the host
(``envs/cartpole/host.py``, ``envs/quadcopter/host.py``) give the JAX engine's episodes (observations, rewards,
terminations, truncations), pass ``check_env``, pickle, and are refused with a message for a task or option they do
not model.

Tolerance: the host step computes in float64 where the JAX step computes in float32, so the cart-pole's
observations agree to float32 rounding (:data:`OBS_ATOL`, several times the differences seen over these episodes)
and every reward and flag is equal; its first observations of an episode are the JAX reset's, bit for bit. The
Goto tasks' tolerances are :data:`GOTO_OBS_ATOL` and :data:`GOTO_REWARD_ATOL`.
"""
from __future__ import annotations

import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import jaxrobo  # noqa: F401  (registers jaxrobo/<id>)
from jaxrobo.interop.gym_adapter import JaxroboEnv
from jaxrobo.speed.compiled import CHAIN

OBS_ATOL = 2e-5
ID = "CartPoleStayUp-v0"


@pytest.fixture(scope="module", params=["analytic", "mjx"])
def pair(request) -> tuple[JaxroboEnv, JaxroboEnv]:
    """The same configuration on both engines (one compile each per module)."""
    return (JaxroboEnv(ID, backend=request.param),
            JaxroboEnv(ID, backend=request.param, engine="numpy"))


def _episode(env: JaxroboEnv, actions: list[int], seed: int | None, options: dict | None = None):
    obs, _ = env.reset(seed=seed, options=options)
    out = [(obs, 0.0, False, False, 0)]
    for a in actions:
        obs, reward, term, trunc, info = env.step(a)
        out.append((obs, reward, term, trunc, info["steps"]))
        if term or trunc:
            break
    return out


def _assert_same(a, b) -> None:
    assert len(a) == len(b)
    np.testing.assert_array_equal(a[0][0], b[0][0])  # the reset's observation: the same state
    for (oa, *ra), (ob, *rb) in zip(a, b):
        assert ob.dtype == np.float32 and ob.shape == oa.shape
        np.testing.assert_allclose(ob, oa, rtol=0, atol=OBS_ATOL)
        assert ra == rb  # reward, terminated, truncated, steps


def test_seeded_episodes_with_random_actions_match_the_jax_engine(pair):
    jax_env, host_env = pair
    rng = np.random.default_rng(0)
    for seed in range(5):
        actions = [int(a) for a in rng.integers(4, size=200)]
        a, b = _episode(jax_env, actions, seed), _episode(host_env, actions, seed)
        assert a[-1][2]  # random actions drop the pole: the episode terminated
        _assert_same(a, b)


def test_unseeded_resets_follow_the_same_key_chain_past_one_reset_chain(pair):
    """Resets without a seed continue the key chain; the host engine draws CHAIN episodes' first states per call,
    so go past one chain, and change a parameter midway (which starts a new chain from the same key)."""
    jax_env, host_env = pair
    rng = np.random.default_rng(1)
    for i in range(CHAIN + 3):
        actions = [int(a) for a in rng.integers(4, size=200)]
        seed = 3 if i == 0 else None
        options = {"init_pole_angle": 0.05} if i == CHAIN // 2 else None
        _assert_same(_episode(jax_env, actions, seed, options), _episode(host_env, actions, seed, options))
    for env in pair:  # back to the default for the other tests on this module's pair
        env.reset(seed=0, options={"init_pole_angle": 0.0})


def test_truncation_at_the_tasks_step_limit():
    """A pole that stays up (no noise, balanced) is truncated at the task's own limit on both engines."""
    kw = dict(backend="analytic", overrides={"max_episode_steps": 12, "init_noise": 0.0})
    a = _episode(JaxroboEnv(ID, **kw), [0, 1] * 20, seed=0)
    b = _episode(JaxroboEnv(ID, engine="numpy", **kw), [0, 1] * 20, seed=0)
    assert len(b) == 13 and b[-1][3] and not b[-1][2]
    _assert_same(a, b)


def test_check_env_passes_and_gym_make_takes_the_engine():
    env = gym.make(f"jaxrobo/{ID}", backend="analytic", engine="numpy")
    assert env.unwrapped.engine == "numpy"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, skip_render_check=True)
        obs, _ = env.reset(seed=1)
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs in env.observation_space and type(reward) is float
    assert type(terminated) is bool and type(truncated) is bool and type(info["steps"]) is int
    env.close()


def test_a_pickled_host_env_goes_on_where_the_original_is():
    env = JaxroboEnv(ID, backend="analytic", engine="numpy")
    env.reset(seed=5)
    env.step(1)
    copy = pickle.loads(pickle.dumps(env))
    for a in (1, 0, 3, 2):
        x, y = env.step(a), copy.step(a)
        np.testing.assert_array_equal(x[0], y[0])
        assert x[1:4] == y[1:4]
    np.testing.assert_array_equal(env.reset()[0], copy.reset()[0])  # the same reset chain


def test_render_draws_the_host_state():
    from jaxrobo.pictures.render import gl_unavailable_reason

    if gl_unavailable_reason() is not None:
        pytest.skip(gl_unavailable_reason())
    a = JaxroboEnv(ID, render_mode="rgb_array", backend="analytic")
    b = JaxroboEnv(ID, render_mode="rgb_array", backend="analytic", engine="numpy")
    for env in (a, b):
        env.reset(seed=2)
        for act in (3, 3, 3):
            env.step(act)
    fa, fb = a.render(), b.render()
    assert fb.shape == fa.shape and fb.dtype == np.uint8
    assert np.mean(fa != fb) < 0.01  # the same picture, up to float32 rounding of the pose
    b.reset(seed=2)
    assert np.any(b.render() != fb)  # the frame follows the host state


@pytest.mark.parametrize("kwargs, words", [
    (dict(engine="torch"), "engine='torch': allowed values are 'jax', 'numpy'"),
    (dict(engine="numpy", randomise=True), "domain randomisation"),
    (dict(engine="numpy", backend="generalized"), "backend='generalized' has no host physics"),
])
def test_refusals_name_the_engine_and_why(kwargs, words):
    with pytest.raises(ValueError, match="engine=") as err:
        JaxroboEnv(ID, **kwargs)
    assert words in str(err.value)


def test_a_task_without_a_host_step_is_refused():
    with pytest.raises(ValueError, match="CartPoleContinuous.* has no host step"):
        JaxroboEnv("CartPoleContinuous-v0", engine="numpy")


def test_the_written_out_control_step_is_the_closed_form_bit_for_bit():
    """The host's control step is ``CartPoleSim.coordinate_step`` on Python floats, written out once as plain
    arithmetic (``straight_line``): the same floats as calling it substep by substep."""
    from jaxrobo.core.scalar import FLOATS

    host = JaxroboEnv(ID, backend="analytic", engine="numpy")._host
    rng = np.random.default_rng(4)
    for values in rng.uniform(-3.0, 3.0, size=(200, 5)).tolist():
        x, th, xd, thd, command = values
        for _ in range(host.n_substeps):
            x, th, xd, thd = host.sim.coordinate_step(x, th, xd, thd, (command,), xp=FLOATS)
        assert host.advance(*values) == (x, th, xd, thd)


# ---- the Goto tasks (envs/quadcopter/host.py) -----------------------------------------------------------------
#: Goto's host step integrates 30 float64 substeps a step where JAX integrates float32 ones: observations agree to
#: float32 round-off accumulated over the episode (about 6e-6 seen over these), rewards to that times the
#: progress weight; flags and step counts are equal. The first observation of an episode is the JAX reset's, drawn
#: by a batched reset (the reset chain), which may round goal_clear one float32 ulp apart from the single reset's.
GOTO_OBS_ATOL, GOTO_REWARD_ATOL = 1e-4, 1e-3


@pytest.fixture(scope="module", params=[("QuadcopterGoto-v2", {}), ("QuadcopterGoto-v1", {"obstacle_kind": "mixed",
                                                                                          "n_obstacles": 3})],
                ids=["v2", "v1-mixed"])
def goto_pair(request) -> tuple[JaxroboEnv, JaxroboEnv]:
    env_id, kw = request.param
    return JaxroboEnv(env_id, **kw), JaxroboEnv(env_id, engine="numpy", **kw)


def test_goto_episodes_with_random_actions_match_the_jax_engine(goto_pair):
    jax_env, host_env = goto_pair
    rng = np.random.default_rng(0)
    ends = set()
    for seed in range(6):
        actions = [int(a) for a in rng.integers(5, size=100)]
        a, b = _episode(jax_env, actions, seed), _episode(host_env, actions, seed)
        assert len(a) == len(b)
        for (oa, *ra), (ob, *rb) in zip(a, b):
            assert ob.dtype == np.float32 and ob.shape == oa.shape
            np.testing.assert_allclose(ob, oa, rtol=0, atol=GOTO_OBS_ATOL)
            assert abs(ra[0] - rb[0]) <= GOTO_REWARD_ATOL and ra[1:] == rb[1:]  # reward; terminated, truncated, steps
        ends.add((b[-1][2], b[-1][3]))
    assert (True, False) in ends  # random flights end by the task's outcome, not only at the step limit


def test_goto_host_step_is_offered_where_it_models_the_task():
    env = gym.make("jaxrobo/QuadcopterGoto-v2", engine="numpy")
    assert env.unwrapped.engine == "numpy"
    obs, _ = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(0)
    assert obs in env.observation_space and type(reward) is float and type(terminated) is bool
    copy = pickle.loads(pickle.dumps(env.unwrapped))  # the written-out control step is written out again
    for a in (3, 0, 1):
        x, y = env.step(a), copy.step(a)
        np.testing.assert_array_equal(x[0], y[0])
        assert x[1:4] == y[1:4]
    env.close()
    with pytest.raises(ValueError, match="QuadcopterGotoTwist.* has no host step"):
        JaxroboEnv("QuadcopterGotoTwist-v0", engine="numpy")
    with pytest.raises(ValueError, match="domain randomisation"):
        JaxroboEnv("QuadcopterGoto-v2", engine="numpy", randomise=True)


def test_make_vec_steps_host_envs_in_sync_mode_and_says_so_otherwise():
    """``gym.make_vec(..., engine="numpy")``: Gymnasium's sync vector env of host-stepped single envs, the same
    episodes as those envs one by one; the vmapped vector env takes the JAX engine only and names the sync mode."""
    venv = gym.make_vec("jaxrobo/QuadcopterGoto-v2", num_envs=2, vectorization_mode="sync", engine="numpy")
    assert all(e.unwrapped.engine == "numpy" for e in venv.envs)
    single = [JaxroboEnv("QuadcopterGoto-v2", engine="numpy") for _ in range(2)]
    obs, _ = venv.reset(seed=3)
    np.testing.assert_array_equal(obs, np.stack([e.reset(seed=3 + i)[0] for i, e in enumerate(single)]))
    for a in ([0, 3], [1, 0], [4, 2]):
        obs, rewards, *_ = venv.step(np.array(a))
        steps = [e.step(x) for e, x in zip(single, a)]
        np.testing.assert_array_equal(obs, np.stack([s[0] for s in steps]))
        assert rewards.tolist() == [s[1] for s in steps]
    venv.close()
    with pytest.raises(ValueError, match="engine='numpy': a JaxroboVectorEnv .* vectorization_mode='sync'"):
        gym.make_vec("jaxrobo/QuadcopterGoto-v2", num_envs=2, engine="numpy")


def test_the_written_out_goto_control_step_is_the_closed_form_bit_for_bit():
    """Goto's host control step (rigid) is the controller and ``dynamics.physics_step`` on Python floats, written
    out once (``straight_line``, its ``where`` as conditional expressions): the same floats as calling them."""
    from envs.quadcopter.dynamics import controller, physics_step
    from jaxrobo.core.scalar import FLOATS

    host = JaxroboEnv("QuadcopterGoto-v1", engine="numpy")._host
    rng = np.random.default_rng(5)
    for _ in range(20):
        quat = rng.normal(size=4)
        q = [*rng.uniform(-2.0, 2.0, 3).tolist(), *(quat / np.linalg.norm(quat)).tolist()]
        v, command = rng.uniform(-2.0, 2.0, 6).tolist(), rng.uniform(-1.0, 1.0, 4).tolist()
        got = host.advance(*q, *v, *command)
        for _ in range(host.n_substeps):
            q, v = physics_step(FLOATS, host.body, q, v, controller(FLOATS, host.control, q, v, command))
        assert list(got) == q + v


def test_straight_line_refuses_a_branch_on_a_computed_value():
    from jaxrobo.core.scalar import straight_line

    assert straight_line(lambda xp, a, b: (xp.minimum(a * 2.0, b), -a / b), ("a", "b"))(1.5, 2.5) == (2.5, -0.6)
    pick = straight_line(lambda xp, a, b: (xp.where(a > b, xp.sqrt(a), xp.arctan2(a, b)),), ("a", "b"))
    assert pick(4.0, 1.0) == (2.0,) and pick(1.0, 1.0) == (np.arctan2(1.0, 1.0),)
    with pytest.raises(TypeError, match="branches on a value it computes"):
        straight_line(lambda xp, a: (a if a else 1.0,), ("a",))


def test_straight_line_writes_out_every_function_of_floats():
    """``FLOATS`` is the one Python-float ``xp`` (host steps, native ports, the exported runner): each of its
    functions, written out by ``straight_line``, gives the same float as called."""
    from jaxrobo.core.scalar import FLOATS, straight_line

    calls = {"sin": lambda xp, a, b: xp.sin(a), "cos": lambda xp, a, b: xp.cos(a),
             "minimum": lambda xp, a, b: xp.minimum(a, b), "maximum": lambda xp, a, b: xp.maximum(a, b),
             "where": lambda xp, a, b: xp.where(a < b, a * 3.0, b), "clip": lambda xp, a, b: xp.clip(a, -0.25, b),
             "abs": lambda xp, a, b: xp.abs(a), "sqrt": lambda xp, a, b: xp.sqrt(xp.abs(b)),
             "arctan2": lambda xp, a, b: xp.arctan2(a, b), "arcsin": lambda xp, a, b: xp.arcsin(xp.clip(a, -1.0, 1.0))}
    assert set(calls) == set(vars(FLOATS))
    for name, call in calls.items():
        written = straight_line(lambda xp, a, b, call=call: (call(xp, a, b),), ("a", "b"))
        for a, b in ((0.3, 0.7), (-0.9, 0.2), (1.5, -2.0)):
            assert written(a, b) == (call(FLOATS, a, b),), (name, a, b)
