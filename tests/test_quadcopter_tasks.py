"""QuadcopterLiveShow-v0 and QuadcopterGoto-v1: reset/step/jit/vmap, the seed's reward rule, termination,
determinism, the success helpers, a tiny training run and the flights picture."""
from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from envs.quadcopter.geometry import BOX, CYLINDER
from envs.quadcopter.robot import Obstacles
from jaxrobo.task.rollout import random_policy, success_rate


@pytest.fixture(scope="module")
def live():
    env = jaxrobo.make("QuadcopterLiveShow-v0")
    return env, jax.jit(env.reset), jax.jit(env.step)


@pytest.fixture(scope="module")
def goto():
    env = jaxrobo.make("QuadcopterGoto-v1")
    return env, jax.jit(env.reset), jax.jit(env.step)


# ---- LiveShow ----------------------------------------------------------------------------------------------
def test_live_show_spec(live):
    env, reset, _ = live
    p = env.default_params
    assert env.num_actions == 5 and env.observation_size == 1 and env.spec.max_episode_steps == 100
    assert (p.goal_x, p.goal_y, p.goal_z, p.max_altitude, p.max_incl, p.speed_value) == (14.0, 1.0, 0.7, 2.0, 0.7, 1.0)
    assert env.options.running_step == 0.3 and env.robot.sim.n_substeps == 30
    s = reset(jax.random.key(0))
    assert s.obs.shape == (1,) and abs(float(s.obs[0])) < 1e-6


def test_live_show_seed_reward(live):
    env, reset, step = live
    s0 = reset(jax.random.key(0))
    fwd = step(s0, 0)  # closer than the best (+100) and forward shaping (+100)
    assert float(fwd.reward) == 200.0 and not bool(fwd.terminated)
    back = step(s0, 3)  # up from rest: farther from z = 0.7 (-100) and up shaping (-150)
    assert float(back.reward) == -250.0
    left = step(s0, 1)  # turning in place creeps forward 0.05 m/s: slightly closer (+100) - 50
    assert float(left.reward) == 50.0
    s = s0
    for _ in range(5):  # climbing past max_altitude 2.0: failure -200 plus the up shaping -150
        s = step(s, 3)
        if bool(s.terminated):
            break
    assert bool(s.terminated) and float(s.reward) == -350.0


def test_live_show_vmap_and_determinism(live):
    env, _, _ = live
    keys = jax.random.split(jax.random.key(3), 8)
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(jax.vmap(env.step))
    s = reset(keys)
    a = jnp.arange(8) % 5
    r1 = step(s, a)
    r2 = step(reset(keys), a)
    np.testing.assert_array_equal(np.asarray(r1.obs), np.asarray(r2.obs))
    assert r1.obs.shape == (8, 1) and bool(jnp.all(jnp.isfinite(r1.obs)))


# ---- Goto --------------------------------------------------------------------------------------------------
def test_goto_reset_layout(goto):
    env, reset, _ = goto
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 64))
    p = env.default_params
    goal, start = np.asarray(s.task.goal), np.asarray(s.task.start)
    horiz = np.linalg.norm(goal[:, :2] - start[:, :2], axis=1)
    assert np.all(horiz >= p.goal_min_dist - 1e-5) and np.all(horiz <= p.goal_max_dist + 1e-5)
    assert len(np.unique(goal[:, 0].round(3))) > 50  # a random goal each episode
    c = np.asarray(s.task.obstacles.center)[:, 0, :2]
    # 'between': on the start-goal segment, within the lateral shift
    d = goal[:, :2] - start[:, :2]
    t = np.sum((c - start[:, :2]) * d, axis=1) / np.sum(d * d, axis=1)
    assert np.all((t > p.obstacle_t_min - 1e-4) & (t < p.obstacle_t_max + 1e-4))
    assert s.obs.shape == (64, 7) and not bool(jnp.any(s.done))


def test_goto_obstacle_ahead_is_seen_and_hit(goto):
    env, reset, step = goto
    s = reset(jax.random.key(1))
    # Place one cylinder 1.5 m straight ahead and fly forward into it.
    yaw = float(env.robot.read_sensors(s.pipeline_state)["rpy"][2])
    ahead = jnp.array([1.5 * np.cos(yaw), 1.5 * np.sin(yaw), 1.5])
    obs = Obstacles(jnp.array([CYLINDER]), ahead[None], jnp.array([[0.4, 0.4, 1.5]]), jnp.array([True]))
    task = s.task.replace(obstacles=obs, goal=jnp.array([8 * np.cos(yaw), 8 * np.sin(yaw), 1.0]))
    s = s.replace(task=task, obs=env._get_obs(s.pipeline_state, task, env.default_params))
    assert abs(float(s.obs[3]) - 1.1) < 1e-3  # forward sonar: 1.5 m to the axis minus the 0.4 m radius
    for _ in range(10):
        s = step(s, 0)
        if bool(s.done):
            break
    assert bool(s.terminated) and bool(s.task.crashed) and not bool(s.task.arrived)
    assert float(s.reward) < -40


def test_goto_arrival_ground_and_workspace(goto):
    env, reset, step = goto
    s = reset(jax.random.key(2))
    pos = env.robot.read_sensors(s.pipeline_state)["pos"]
    none = s.task.obstacles.replace(active=jnp.zeros_like(s.task.obstacles.active))
    near = s.replace(task=s.task.replace(goal=pos + jnp.array([0.0, 0.0, -0.2]), obstacles=none))
    arrived = step(near, 4)
    assert bool(arrived.terminated) and bool(arrived.task.arrived) and float(arrived.reward) > 50
    low = s.replace(task=s.task.replace(obstacles=none))
    for _ in range(8):  # no altitude floor in Goto: flying down ends on the ground
        low = step(low, 4)
        if bool(low.done):
            break
    assert bool(low.task.crashed) and float(env.robot.read_sensors(low.pipeline_state)["pos"][2]) <= 0.26
    small = env.default_params.replace(workspace=0.05)
    out = jax.jit(env.step)(s.replace(task=s.task.replace(obstacles=none)), 0, small)
    assert bool(out.terminated) and bool(out.task.crashed)


def test_a_non_finite_step_keeps_the_task_variables_as_they_were(goto):
    """The NaN guard: the episode ends with zero reward, the last finite observation and the task's variables
    (goal, prev_dist, arrived, crashed) as they were; an outcome read from NaNs is not taken. The task kernel does
    the same (tests/test_quadcopter_goto_kernel.py flies a NaN env against these hooks)."""
    env, reset, step = goto
    s = reset(jax.random.key(4))
    ps = s.pipeline_state
    bad = s.replace(pipeline_state=ps.replace(qpos=ps.qpos.at[2].set(jnp.nan)))
    out = step(bad, 0)
    assert bool(out.physics_nan) and bool(out.terminated) and float(out.reward) == 0.0
    np.testing.assert_array_equal(np.asarray(out.obs), np.asarray(s.obs))
    for (path, new), old in zip(jax.tree_util.tree_flatten_with_path(out.task)[0], jax.tree.leaves(s.task)):
        np.testing.assert_array_equal(np.asarray(new), np.asarray(old), err_msg=jax.tree_util.keystr(path))


def test_goto_box_and_random_placement():
    env = jaxrobo.make("QuadcopterGoto-v1", obstacle_kind="mixed", obstacle_placement="random", n_obstacles=4)
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 16))
    kinds = np.asarray(s.task.obstacles.kind)
    assert kinds.shape == (16, 4) and set(np.unique(kinds)) <= {BOX, CYLINDER} and len(np.unique(kinds)) == 2
    c = np.asarray(s.task.obstacles.center)[..., :2]
    assert np.all(np.linalg.norm(c - np.asarray(s.task.start)[:, None, :2], axis=-1) > 1.0)


def test_goto_random_policy_success_is_low(goto):
    env, _, _ = goto
    stats = success_rate(env, random_policy(5), jax.random.key(0), 16)
    assert stats["success"] <= 0.25 and abs(stats["success"] + stats["failure"] + stats["timeout"] - 1) < 1e-6


def test_goto_training_smoke_and_flights_png(tmp_path):
    """A tiny shared-table training run compiles, stays finite, and its table flies in the picture."""
    from jaxrobo import show as flights
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    spec = resolve("QuadcopterGoto-v1", overrides={"n_envs": 4, "nepisodes": 3, "nsteps": 15, "chunk_steps": 15,
                                                    "eval_episodes": 0})
    res = train(spec.env, spec.config, spec.agent_params)
    assert np.all(np.isfinite(res.returns)) and res.q.shape[-1] == 5 and res.env_steps > 0
    out = flights.fly(spec, res.q, 0, 2, 0)
    png = os.path.join(tmp_path, "flights.png")
    flights.draw(out, "smoke", png)
    assert os.path.getsize(png) > 10_000
    assert out["pos"].shape == (2, spec.env.spec.max_episode_steps + 1, 3)
    parser = argparse.ArgumentParser()
    flights.configure_parser(parser)
    assert flights.run(parser.parse_args([])) == 2  # neither a run nor an env: usage error


def test_jaxrobos_programs_trace_an_envs_reset_once_with_the_numbers_of_the_hooks_inline():
    """Under a plan's tracing (jaxrobo's own programs) an env's resets share one trace of its reset per
    trace-time choice: two batches of resets in one program run the hooks' Python once, and the program's numbers
    are those of the hooks traced inline, as a caller's own jit traces them. After use the env still deep-copies
    (the copy makes its own) and the trace-reuse key does not see whether it was used."""
    import copy

    from jaxrobo.speed import reuse
    from jaxrobo.speed.plan import ExecutionPlan

    env = jaxrobo.make("QuadcopterGoto-v2")
    described = reuse.describe(env)
    calls = []
    hook = env._get_obs
    env._get_obs = lambda *a: calls.append(1) or hook(*a)
    keys = jax.random.split(jax.random.key(0), 6)

    def two(keys):
        return jax.vmap(env.reset)(keys), jax.vmap(env.reset)(keys[:2])

    inline = jax.jit(two)(keys)
    assert len(calls) == 2
    plan = ExecutionPlan()
    shared = jax.jit(plan.traced(two))(keys)
    assert len(calls) == 3  # both batches in one trace of the reset
    jax.jit(plan.traced(lambda k: jax.vmap(env.reset)(k)))(keys[:3])
    assert len(calls) == 3  # and other programs reuse it

    def same(xs, ys):
        for a, b in zip(jax.tree.leaves(xs), jax.tree.leaves(ys), strict=True):
            if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
                a, b = jax.random.key_data(a), jax.random.key_data(b)
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    same(inline, shared)
    del env._get_obs
    assert reuse.describe(env) == described
    again = copy.deepcopy(env)
    with plan.tracing():
        out = jax.jit(jax.vmap(again.reset))(keys)
    same(inline[0], out)
