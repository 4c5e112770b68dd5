"""ArmReach-v0 (envs/arm/robot.py, envs/arm/reach.py): the MJCF under MJX against native MuJoCo, the fingertip
sensor, the environment card (actions, observation, reward, termination, reset), and the ordinary tools on it:
``jaxrobo check``, Gymnasium's checker through ``gym.make``, rendering, ``jaxrobo train`` and ``sweep`` and a
throughput row. Everything shares one built env and its compiled reset/step."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import gymnasium as gym
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import jaxrobo
from envs.arm import reach as arm_reach
from envs.arm.robot import ELBOW_MAX, FORE, UPPER, ArmRobot, fingertip
from jaxrobo.physics.sim import JointState
from jaxrobo.pictures import render
from jaxrobo.cli import main

ID = "ArmReach-v0"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def arm():
    """ArmReach-v0 with its jitted reset and step, shared by every test here (params always passed, so a test
    with other parameter values reuses the same compiled step)."""
    env = jaxrobo.make(ID)
    reset_c, step_c = jax.jit(env.reset), jax.jit(env.step)
    default = env.default_params
    return (env, lambda key, p=None: reset_c(key, default if p is None else p),
            lambda s, a, p=None: step_c(s, a, default if p is None else p))


@pytest.fixture(scope="module")
def robot(arm):
    return arm[0].robot


def _native(robot: ArmRobot):
    m = robot.sim.mj_model
    return m, mujoco.MjData(m)


# ---- the robot: MJX = native MuJoCo, sensors ------------------------------------------------------------------
def test_mjx_matches_native_mujoco_over_300_steps(robot):
    """The shipped MJCF (both servos, the elbow's ctrlrange clamp) stepped by MJX and by native MuJoCo from the
    same state under the same set-points (some beyond the elbow's range), in float32: 3 s of motion."""
    m, d = _native(robot)
    t = np.arange(300) * m.opt.timestep
    ctrl = np.stack([1.5 * np.sin(1.3 * t), 1.4 + 1.8 * np.sin(2.1 * t)], axis=1)  # elbow set-point beyond [0, 2.8]
    q0 = np.array([0.3, 1.0])
    d.qpos[:] = q0
    native = []
    for u in ctrl:
        d.ctrl[:] = u
        mujoco.mj_step(m, d)
        native.append(np.concatenate([d.qpos, d.qvel]))
    native = np.array(native)

    def body(s, u):
        s = robot.sim.physics_step(s, u)
        return s, jnp.concatenate([robot.sim.qpos(s), robot.sim.qvel(s)])

    s0 = robot.sim.init(*robot.init_pose(jnp.asarray(q0)))
    _, traj = jax.jit(lambda s: jax.lax.scan(body, s, jnp.asarray(ctrl, jnp.float32)))(s0)
    assert np.ptp(native[:, 0]) > 2.0 and native[:, 1].max() > 2.5, "the trajectory should move both joints far"
    assert native[:, 1].max() < ELBOW_MAX + 0.1  # the clamp holds the elbow near its range
    err = np.abs(np.asarray(traj) - native)
    # Observed: 3e-7 rad and 1e-5 rad/s (float32 round-off, over velocities up to 7 rad/s).
    assert err[:, :2].max() < 1e-5 and err[:, 2:].max() < 1e-4, err.max(axis=0)


def test_fingertip_sensor_is_the_mjcf_site(robot):
    m, d = _native(robot)
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "fingertip")
    for q in np.random.default_rng(0).uniform([-np.pi, 0.0], [np.pi, ELBOW_MAX], size=(8, 2)):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(np.asarray(fingertip(jnp.asarray(q))), d.site_xpos[site][:2], atol=1e-6)
    s = robot.sim.init(*robot.init_pose(jnp.array([0.4, 1.2])))
    sensors = robot.read_sensors(s)
    np.testing.assert_allclose(sensors["q"], [0.4, 1.2], atol=1e-6)
    np.testing.assert_allclose(sensors["tip"], fingertip(jnp.array([0.4, 1.2])), atol=1e-6)
    assert bool(robot._check_all_systems_ready(s))


def test_a_servo_step_settles_within_two_control_steps(robot):
    """The MJCF's claim behind the actions: a 0.1 rad set-point step is mostly done after one 0.1 s control step
    and settled after two, so the observation is (close to) a function of the set-points. Checked on native
    MuJoCo, which MJX matches (above)."""
    m, d = _native(robot)
    n = robot.sim.n_substeps
    for elbow in (0.3, 2.5):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = [0.0, elbow]
        d.ctrl[:] = [0.1, elbow + 0.1]
        mujoco.mj_step(m, d, nstep=n)
        moved = d.qpos - [0.0, elbow]
        assert np.all(moved > 0.08) and np.all(moved < 0.12), moved
        mujoco.mj_step(m, d, nstep=n)
        np.testing.assert_allclose(d.qpos - [0.0, elbow], 0.1, atol=0.006)


# ---- the closed form (backend "analytic", the default preset's) ----------------------------------------------
# In a fresh interpreter: float64 must be on before JAX starts. The closed form steps the shipped MJCF through 300
# physics steps beside native MuJoCo (both servos, the elbow's set-point beyond its range), at nominal physics and
# with the masses and damping scaled (domain randomisation's factors against the model edited the same way).
_X64_SCRIPT = """
import jax, jax.numpy as jnp, mujoco, numpy as np
from envs.arm.robot import ArmRobot
from jaxrobo.physics.sim import JointState
robot = ArmRobot("analytic", running_step=0.01, timestep=0.01)
for mass, damping in ((1.0, 1.0), (1.3, 0.6)):
    m = robot.sim.mj_model
    saved = (m.body_mass.copy(), m.body_inertia.copy(), m.dof_damping.copy())
    m.body_mass[:] *= mass; m.body_inertia[:] *= mass; m.dof_damping[:] *= damping
    t = np.arange(300) * m.opt.timestep
    ctrl = np.stack([1.5 * np.sin(1.3 * t), 1.4 + 1.8 * np.sin(2.1 * t)], axis=1)
    d = mujoco.MjData(m); d.qpos[:] = [0.3, 1.0]
    native = []
    for u in ctrl:
        d.ctrl[:] = u; mujoco.mj_step(m, d); native.append(np.concatenate([d.qpos, d.qvel]))
    m.body_mass[:], m.body_inertia[:], m.dof_damping[:] = saved
    f = None if mass == 1.0 else {"link_mass": jnp.float64(mass), "damping": jnp.float64(damping)}
    def body(s, u):
        s = robot.sim.physics_step(s, u, f)
        return s, jnp.concatenate([s.qpos, s.qvel])
    s0 = JointState(jnp.array([0.3, 1.0]), jnp.zeros(2))  # float64: not through sim.init, which casts
    _, traj = jax.jit(lambda s: jax.lax.scan(body, s, jnp.asarray(ctrl)))(s0)
    native = np.array(native)
    print("MAXERR", mass, np.abs(np.asarray(traj) - native).max(), np.ptp(native[:, 0]), native[:, 1].max())
"""


def test_analytic_backend_matches_native_mujoco_to_float64_roundoff():
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", _X64_SCRIPT], capture_output=True, text=True, env=env, timeout=300,
                         cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [ln.split() for ln in out.stdout.splitlines() if ln.startswith("MAXERR")]
    assert [r[1] for r in rows] == ["1.0", "1.3"], out.stdout
    for _, mass, err, sweep, elbow in rows:
        assert float(sweep) > 2.0 and float(elbow) > 2.5, "the trajectory should move both joints far"
        assert float(err) < 1e-10, f"link_mass={mass}: the closed form and native MuJoCo differ by {err}"


def test_analytic_backend_tracks_mjx_in_float32():
    """The task on either backend, the same actions from the same reset: float32 round-off apart over 40 steps."""
    traces = []
    for backend in ("mjx", "analytic"):
        env = jaxrobo.make(ID, backend=backend)
        step = jax.jit(env.step)
        state, obs = env.reset(jax.random.key(3)), []
        for t in range(40):
            state = step(state, (0, 2, 2, 1, 3, 0)[t % 6])
            obs.append(np.asarray(state.obs))
        traces.append(np.array(obs))
    assert np.ptp(traces[0][:, 0]) > 0.3, "the elbow should move"
    np.testing.assert_allclose(traces[1], traces[0], atol=1e-5)


def test_analytic_backend_at_nominal_factors_steps_the_nominal_physics():
    """Domain randomisation's factors of 1 step the nominal physics (to float32 round-off: the nominal step sums its
    constants on the host), and other factors another physics (native MuJoCo agrees with them above)."""
    sim = ArmRobot("analytic", running_step=0.01, timestep=0.01).sim
    k = jax.random.split(jax.random.key(0), 3)
    q = jax.random.uniform(k[0], (64, 2), minval=-2.0, maxval=2.0)
    v = jax.random.uniform(k[1], (64, 2), minval=-4.0, maxval=4.0)
    u = jax.random.uniform(k[2], (64, 2), minval=-1.0, maxval=3.0)
    nominal = jax.jit(jax.vmap(lambda q, v, u: sim.physics_step(JointState(q, v), u)))(q, v, u)
    drawn = jax.jit(jax.vmap(lambda q, v, u, f: sim.physics_step(JointState(q, v), u, f)))
    one = drawn(q, v, u, {"link_mass": jnp.ones(64), "damping": jnp.ones(64)})
    other = drawn(q, v, u, {"link_mass": jnp.full(64, 1.5), "damping": jnp.ones(64)})
    np.testing.assert_allclose(np.asarray(one.qvel), np.asarray(nominal.qvel), rtol=1e-6, atol=1e-5)
    assert np.abs(np.asarray(other.qvel) - np.asarray(nominal.qvel)).max() > 1e-3


def test_analytic_backend_refuses_what_it_cannot_model():
    from envs.arm.dynamics import ArmSim
    from envs.arm.robot import JOINTS, MJCF
    from jaxrobo.physics.sim import load_model

    def edited(edit):
        return load_model(MJCF, edit=edit)

    with pytest.raises(ValueError, match="limits"):
        ArmSim(edited(lambda s: setattr(s.joint("elbow"), "range", [0, 2])), JOINTS)
    with pytest.raises(ValueError, match="stiffness"):
        ArmSim(edited(lambda s: setattr(s.joint("shoulder"), "stiffness", [1.0, 0, 0])), JOINTS)
    with pytest.raises(ValueError, match="axes must be"):
        ArmSim(edited(lambda s: setattr(s.joint("elbow"), "axis", [0, 1, 0])), JOINTS)
    with pytest.raises(ValueError, match="backend='mjx'"):
        ArmSim(edited(None), ("shoulder", "no_such_joint"))


def test_the_default_preset_trains_on_the_closed_form():
    from jaxrobo.training.run import resolve

    spec = resolve(ID)
    assert spec.env.robot.sim.backend == "analytic" and spec.env.robot.sim.n_substeps == 10
    assert jaxrobo.make(ID).robot.sim.backend == "mjx"  # the task's own default (gym.make) stays MJX


# ---- the task: the environment card ---------------------------------------------------------------------------
def test_card_is_the_module_docstring_first():
    doc = arm_reach.__doc__
    assert doc.index("Environment card") < 400
    for word in ("Actions", "Observation", "Reward", "Termination", "Control", "Reset", "Learning", "Parameters",
                 ">= 80 %", "median"):
        assert word in doc
    target = arm_reach.ArmReach.learning_target
    assert (target.metric, target.threshold) == ("success_rate", 0.8)


def test_spaces_and_reset(arm):
    env, reset, _ = arm
    assert env.num_actions == 4 and env.observation_size == 3 and env.spec.max_episode_steps == 100
    assert env.observation_space().names == ("elbow", "goal_x", "goal_y")
    p = env.default_params
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(1), 256))
    q = np.asarray(jax.vmap(env.robot.joint_angles)(states.pipeline_state))
    goal, tip = np.asarray(states.task.goal), np.asarray(fingertip(jnp.asarray(q)))
    assert q[:, 1].min() >= p.elbow_min and q[:, 1].max() <= p.elbow_max
    assert np.ptp(q[:, 0]) > 5.0  # shoulder anywhere in [-pi, pi]
    np.testing.assert_allclose(np.asarray(states.task.command), q, atol=1e-6)  # set-points start at the pose
    # Goals are fingertips of random poses in the same elbow range: reachable, and (almost always) far enough.
    r = np.linalg.norm(goal, axis=1)
    assert r.max() <= 0.9 + 1e-6 and r.min() >= np.sqrt(0.5**2 + 0.4**2 + 2 * 0.5 * 0.4 * np.cos(p.elbow_max)) - 1e-5
    assert np.mean(np.linalg.norm(goal - tip, axis=1) >= p.min_goal_dist) > 0.99
    assert np.all(np.asarray(states.task.prev_dist) == pytest.approx(np.linalg.norm(goal - tip, axis=1), abs=1e-5))
    # The observation: the elbow, and the goal seen from the fingertip in the upper arm's frame.
    c, s = np.cos(q[:, 0]), np.sin(q[:, 0])
    rel = goal - tip
    frame = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)
    np.testing.assert_allclose(np.asarray(states.obs), np.column_stack([q[:, 1], frame]), atol=1e-5)
    assert not bool(jnp.any(states.terminated))


@pytest.mark.parametrize("action,joint,sign", [(0, 0, -1), (1, 0, 1), (2, 1, -1), (3, 1, 1)])
def test_each_action_moves_its_joint(arm, action, joint, sign):
    env, reset, step = arm
    s0 = reset(jax.random.key(3))
    s1 = step(s0, action)
    dq = np.asarray(env.robot.joint_angles(s1.pipeline_state) - env.robot.joint_angles(s0.pipeline_state))
    dc = np.asarray(s1.task.command - s0.task.command)
    assert dc[joint] == pytest.approx(sign * 0.1, abs=1e-6) and dc[1 - joint] == 0.0
    assert sign * dq[joint] > 0.08 and abs(dq[1 - joint]) < 0.02
    # Reward: progress_reward per m closer minus the step cost (no bonus before reaching).
    p = env.default_params
    want = p.progress_reward * (float(s0.task.prev_dist) - float(s1.task.prev_dist)) - p.step_cost
    assert float(s1.reward) == pytest.approx(want, abs=1e-5)


def test_the_elbow_set_point_is_clipped_to_its_range(arm):
    env, reset, step = arm
    s = reset(jax.random.key(4))
    for _ in range(30):
        s = step(s, 3)
    assert float(s.task.command[1]) == pytest.approx(ELBOW_MAX)
    for _ in range(35):
        s = step(s, 2)
    assert float(s.task.command[1]) == 0.0


def _inverse_kinematics(goal: jax.Array) -> jax.Array:
    """The joint angles (elbow in ``[0, pi]``) that put the fingertip on ``goal``."""
    r2 = jnp.sum(goal**2)
    elbow = jnp.arccos(jnp.clip((r2 - UPPER**2 - FORE**2) / (2 * UPPER * FORE), -1.0, 1.0))
    shoulder = jnp.arctan2(goal[1], goal[0]) - jnp.arctan2(FORE * jnp.sin(elbow), UPPER + FORE * jnp.cos(elbow))
    return jnp.stack([shoulder, elbow])


def test_a_model_based_policy_reaches_the_goal_with_the_bonus(arm):
    """Stepping the set-points towards the goal's inverse kinematics reaches every goal: the task is solvable
    within the step limit, and termination, the bonus and the arrival flag come together. The set-points move on
    a 0.1 rad lattice, so the nearest lattice pose is up to 0.05 rad per joint off (up to 0.065 m at the
    fingertip): this policy is given a 0.07 m tolerance (a learner can also choose among near poses)."""
    env, reset, step = arm
    p = env.default_params.replace(goal_tolerance=0.07)

    @jax.jit
    def choose(s):
        err = jnp.angle(jnp.exp(1j * (_inverse_kinematics(s.task.goal) - s.task.command)))  # wrapped to (-pi, pi]
        joint = jnp.argmax(jnp.abs(err))
        return 2 * joint + (err[joint] > 0).astype(jnp.int32)

    for seed in range(3):
        s = reset(jax.random.key(10 + seed), p)
        for _ in range(int(p.max_episode_steps)):
            prev = s
            s = step(s, choose(s), p)
            if bool(s.terminated | s.truncated):
                break
        assert bool(s.terminated) and bool(s.task.arrived) and not bool(s.task.crashed)
        assert float(jnp.linalg.norm(s.obs[1:])) < p.goal_tolerance
        progress = p.progress_reward * (float(prev.task.prev_dist) - float(s.task.prev_dist))
        assert float(s.reward) == pytest.approx(progress - p.step_cost + p.reach_bonus, abs=1e-4)


def test_params_out_of_range_are_refused_naming_the_field():
    with pytest.raises(jaxrobo.core.config.ConfigError, match="goal_tolerance"):
        jaxrobo.make(ID, goal_tolerance=0.0)
    with pytest.raises(jaxrobo.core.config.ConfigError, match="timestep"):
        jaxrobo.make(ID, timestep=0.05)


# ---- the ordinary tools on the new id -------------------------------------------------------------------------
@pytest.mark.slow
def test_jaxrobo_check_quick_passes(capsys):
    assert main(["check", ID, "--quick"]) == 0
    out = capsys.readouterr().out
    assert "FAIL" not in out and "checks pass" in out


def test_gymnasium_check_env_through_gym_make():
    from gymnasium.utils.env_checker import check_env

    genv = gym.make(f"jaxrobo/{ID}")
    try:
        assert genv.spec.max_episode_steps == 100
        check_env(genv.unwrapped, skip_render_check=True)
        obs, _ = genv.reset(seed=0)
        obs, reward, terminated, truncated, _ = genv.step(1)
        assert obs.shape == (3,) and obs.dtype == np.float32 and isinstance(reward, float)
    finally:
        genv.close()


_GL = render.gl_unavailable_reason()


@pytest.mark.skipif(_GL is not None, reason=str(_GL))
def test_render_shows_the_arm_and_the_goal(arm):
    env, reset, step = arm
    s = reset(jax.random.key(0))
    frame = render.render_frame(env, s, 96, 96)
    assert frame.shape == (96, 96, 3) and frame.dtype == np.uint8 and frame.std() > 1.0
    red = (frame[..., 0] > 150) & (frame[..., 1] < 90) & (frame[..., 2] < 90)
    assert red.any(), "the goal marker (render_extras) is drawn"
    moved = step(step(s, 1), 1)
    assert not np.array_equal(frame, render.render_frame(env, moved, 96, 96))


@pytest.mark.slow
def test_tiny_train_writes_a_run_directory(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--env", ID, "--n-envs", "2", "--nepisodes", "2", "--set", "nsteps=10",
                 "--set", "chunk_steps=10", "--set", "eval_episodes=1", "--set", "eval_envs=1", "--no-progress",
                 "--out", str(out)]) == 0
    assert (out / "config.yaml").exists()
    assert "ArmReach-v0" in (out / "config.yaml").read_text()
    assert any(p.name.startswith("episodes") for p in out.iterdir())


@pytest.mark.slow
def test_tiny_sweep(tmp_path):
    out = tmp_path / "sweep"
    assert main(["sweep", "--env", ID, "--grid", "alpha=0.1,0.3", "--n-envs", "2", "--nepisodes", "2",
                 "--nsteps", "10", "--no-plots", "--out", str(out)]) == 0
    import csv

    with open(out / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    # a row per grid value and seed (4 by default), each trained (2 episodes of 10 steps on each of 2 envs) and
    # evaluated on the arm's learning figure
    assert sorted((float(r["alpha"]), int(r["seed"])) for r in rows) == [(a, s) for a in (0.1, 0.3) for s in range(4)]
    assert all(int(r["episodes_done"]) == 2 and int(r["env_steps"]) == 40 for r in rows), rows
    assert all(0.0 <= float(r["eval_success_rate"]) <= 1.0 for r in rows), rows
    assert json.loads((out / "summary.json").read_text())["n_rows"] == 8


@pytest.mark.slow
def test_throughput_row(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": str(tmp_path / "cache"),
           "XLA_FLAGS": "--xla_backend_optimization_level=0"}
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "throughput.py"), "--commands", "none",
           "--time-to-trained", "none", "--envs", ID, "--n-envs", "4", "--steps", "5", "--repeats", "1",
           "--learners", "qlearn", "--peers", "none", "--no-plot", "--out", str(tmp_path / "out")]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [r for r in json.loads((tmp_path / "out" / "throughput.json").read_text())["rows"] if r["env"] == ID]
    assert {r["mode"] for r in rows} == {"env", "qlearn"}
    assert all(r["status"] == "ok" and r["steps_per_s"] > 0 for r in rows), rows


def test_the_step_is_one_source_over_numpy_and_jax():
    """The action map, observation and success test are the same functions over numpy (the native port's float64)
    and jax.numpy (the env's float32): on random poses, goals and set-points they agree to float32 round-off."""
    from envs.arm.reach import ACTION_DELTAS, observation, reached, set_points

    rs = np.random.default_rng(0)
    for _ in range(50):
        q = rs.uniform([-np.pi, 0.0], [np.pi, ELBOW_MAX])
        goal = rs.uniform(-0.9, 0.9, 2)
        command = rs.uniform([-np.pi, -0.2], [np.pi, ELBOW_MAX + 0.2])
        delta = np.asarray(ACTION_DELTAS[rs.integers(len(ACTION_DELTAS))])
        obs_np = observation(q, goal, np)
        obs_jx = np.asarray(observation(jnp.asarray(q, jnp.float32), jnp.asarray(goal, jnp.float32)))
        assert obs_np.dtype == np.float32 and obs_jx.dtype == np.float32
        np.testing.assert_allclose(obs_np, obs_jx, atol=2e-6)
        sp_np = set_points(command, delta, 0.1, np)
        sp_jx = np.asarray(set_points(jnp.asarray(command, jnp.float32), jnp.asarray(delta, jnp.float32), 0.1))
        np.testing.assert_allclose(sp_np, sp_jx, atol=1e-6)
        assert 0.0 <= sp_np[1] <= ELBOW_MAX
        assert bool(reached(obs_np, 0.5, np)) == bool(reached(jnp.asarray(obs_jx), 0.5)) or abs(
            np.linalg.norm(obs_np[1:]) - 0.5) < 1e-5
