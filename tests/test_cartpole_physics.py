"""The MJX cart-pole matches native MuJoCo, and each control type moves the cart as commanded."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from envs import asset_path
from envs.cartpole.robot import CartPoleRobot
from jaxrobo.physics.sim import JointState, MjxState, check_same_dynamics, load_model, make_simulator, mjx

# Runs in a fresh interpreter because float64 must be switched on before JAX starts. Each backend steps the
# robot's own model (the MJCF as shipped) through 500 physics steps of a swinging trajectory beside native MuJoCo.
_X64_SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, mujoco, numpy as np
    from envs.cartpole.robot import CartPoleRobot
    from jaxrobo.physics.sim import JointState, MjxState
    cases = [("mjx", "velocity")] + [("analytic", c) for c in ("velocity", "position", "effort")]
    for backend, control_type in cases:
        robot = CartPoleRobot(control_type, backend, running_step=0.01, timestep=0.01)
        m = robot.sim.mj_model
        ctrl = 0.8 * np.sin(np.arange(500) * 0.05)
        d = mujoco.MjData(m); d.qpos[:] = [0.1, 0.2]
        native = []
        for u in ctrl:
            d.ctrl[0] = u; mujoco.mj_step(m, d); native.append(np.concatenate([d.qpos, d.qvel]))
        q0, v0 = jnp.array([0.1, 0.2]), jnp.zeros(2)  # float64: not through sim.init, which casts to float32
        s0 = MjxState.of(robot.sim._data0).replace(qpos=q0, qvel=v0) if backend == "mjx" else JointState(q0, v0)
        def body(s, u):
            s = robot.sim.physics_step(s, jnp.array([u]))
            return s, jnp.concatenate([robot.sim.qpos(s), robot.sim.qvel(s)])
        _, traj = jax.jit(lambda s: jax.lax.scan(body, s, jnp.asarray(ctrl)))(s0)
        err = np.abs(np.asarray(traj) - np.array(native)).max()
        print(f"{backend} {control_type} MAXERR {err:.3e} SWING {np.abs(np.array(native)[:, 1]).max():.3f}")
""")


@pytest.fixture(scope="module")
def x64_errors() -> dict[tuple[str, str], tuple[float, float]]:
    """``(backend, control_type) -> (max error vs native MuJoCo, max pole swing)`` over 500 float64 steps."""
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", _X64_SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [ln.split() for ln in out.stdout.splitlines() if "MAXERR" in ln]
    return {(r[0], r[1]): (float(r[3]), float(r[5])) for r in rows}


def test_mjx_matches_native_mujoco_over_500_steps(x64_errors):
    err, swing = x64_errors[("mjx", "velocity")]
    assert swing > 1.0, "the trajectory should exercise the dynamics (the pole falls and swings)"
    assert err < 1e-5, f"MJX and native MuJoCo differ by {err} over 500 steps"


def test_single_step_float32_matches_native():
    robot = CartPoleRobot("effort", "mjx", running_step=0.01, timestep=0.01)
    m = robot.sim.mj_model
    rng = np.random.default_rng(0)
    step = jax.jit(robot.sim.physics_step)
    for _ in range(5):
        q, v, u = rng.normal(size=2) * 0.3, rng.normal(size=2), rng.normal(size=1) * 5
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, v, u
        mujoco.mj_step(m, d)
        out = step(robot.sim.init(q, v), jnp.asarray(u, jnp.float32))
        np.testing.assert_allclose(np.asarray(out.qpos), d.qpos, atol=1e-5)
        np.testing.assert_allclose(np.asarray(out.qvel), d.qvel, atol=1e-5)


def _hold(robot: CartPoleRobot, command: float, seconds: float) -> np.ndarray:
    """Hold one command for ``seconds``; returns the sensor trace [steps, 4]."""
    state = robot.sim.init(*robot.init_pose(0.0, 0.0))
    n = int(round(seconds / robot.sim.running_step))

    def body(s, _):
        s = robot.advance(s, jnp.array([command], jnp.float32))
        return s, robot.read_sensors(s)

    return np.asarray(jax.jit(lambda s: jax.lax.scan(body, s, None, length=n))(state)[1])


@pytest.mark.parametrize("control_type,command,check", [
    ("velocity", 0.5, lambda tr: abs(tr[-1, 1] - 0.5) < 0.02),          # cart velocity tracks 0.5 m/s
    ("position", 0.3, lambda tr: abs(tr[-1, 0] - 0.3) < 0.03),          # cart settles at 0.3 m
    ("effort", 1.0, lambda tr: tr[-1, 0] > 0.05 and np.all(np.diff(tr[:10, 1]) > 0)),  # force accelerates +x
])
def test_control_types_move_the_cart_as_commanded(control_type, command, check):
    robot = CartPoleRobot(control_type, "mjx", running_step=0.04, timestep=0.01)
    trace = _hold(robot, command, 2.0 if control_type != "velocity" else 1.0)
    assert np.all(np.isfinite(trace))
    assert check(trace), f"{control_type}: final state {trace[-1]}"


@pytest.mark.parametrize("backend", ["generalized", "positional", "spring"])
def test_brax_pipelines_run_the_same_task(backend):
    import jaxrobo

    env = jaxrobo.make("CartPoleStayUp-v0", backend=backend, init_noise=0.0)
    state = env.reset(jax.random.key(0))
    step = jax.jit(env.step)
    for _ in range(3):
        state = step(state, 3)  # right big: the velocity set-point rises 0.16 m/s a step
    assert np.all(np.isfinite(np.asarray(state.obs)))
    if backend != "spring":  # Brax's spring pipeline is an approximation that drifts on this stiff actuator
        assert state.obs[0] > 0.0 and state.obs[1] > 0.2, f"{backend}: {state.obs}"


# ---- the physics-only model MJX integrates -------------------------------------------------------------------
@pytest.mark.parametrize("xml,nu", [("cartpole.xml", 1), ("quadcopter.xml", 4)])
def test_physics_only_model_has_the_same_dynamics_bit_for_bit(xml, nu):
    """Without visual geoms, camera and light, native MuJoCo steps the same trajectory bit for bit (the MJX test
    above runs the robot's physics-only model against native MuJoCo on the whole one)."""
    keep = ("effort",) if xml == "cartpole.xml" else None
    full, lean = (load_model(asset_path(xml), keep_actuators=keep, physics_only=p) for p in (False, True))
    assert full.ngeom > 0 and full.nlight > 0 and (lean.ngeom, lean.ncam, lean.nlight) == (0, 0, 0)
    check_same_dynamics(full, lean)
    traces = []
    for m in (full, lean):
        d = mujoco.MjData(m)
        mujoco.mj_resetData(m, d)
        d.qpos[:2] += 0.1
        trace = []
        for t in range(300):
            d.ctrl[:] = np.sin(0.05 * t + np.arange(nu)) + (0.07 if nu == 4 else 0.0)  # quadcopter: ~hover thrust
            mujoco.mj_step(m, d)
            trace.append(np.concatenate([d.qpos, d.qvel]))
        traces.append(np.array(trace))
    assert np.abs(traces[0][-1] - traces[0][0]).max() > 0.05, "the model should move"
    np.testing.assert_array_equal(traces[1], traces[0])


def test_mjx_integrates_the_physics_only_model_and_refuses_another():
    robot = CartPoleRobot("velocity", "mjx")
    assert robot.sim.mj_model.ngeom == 4 and robot.sim.model.ngeom == 0  # rendering keeps the whole model
    other = load_model(asset_path("cartpole.xml"), keep_actuators=("position",), physics_only=True)
    with pytest.raises(ValueError, match="physics_model differs from mj_model in actuator"):
        make_simulator(robot.sim.mj_model, "mjx", physics_model=other)


def test_mjx_state_steps_like_the_full_data_and_forward_rebuilds_it():
    """The env carries only MuJoCo's integration state (MjxState); stepping it gives the same qpos/qvel bit for
    bit as stepping the whole mjx.Data, and ``forward`` rebuilds the derived quantities (body poses)."""
    robot = CartPoleRobot("effort", "mjx", running_step=0.01, timestep=0.01)
    sim = robot.sim
    state = sim.init(jnp.array([0.1, 0.3]), jnp.array([0.2, -0.5]))
    assert isinstance(state, MjxState) and sum(x.size for x in jax.tree.leaves(state)) == 1 + 2 + 2 + 0 + 2
    full = sim._data0.replace(**state.fields())
    ctrl = jnp.array([1.5])
    for _ in range(3):
        state = jax.jit(sim.physics_step)(state, ctrl)
        full = jax.jit(lambda d: mjx.step(sim.model, d.replace(ctrl=ctrl)))(full)
    for name in ("time", "qpos", "qvel"):
        np.testing.assert_array_equal(np.asarray(getattr(state, name)), np.asarray(getattr(full, name)), name)
    # The cart-pole can have no constraint rows (contacts off, no limits), so nothing reads the solver's warm
    # start: the carried state keeps it at zero (MjxSim.physics_step), and the integration above is unchanged.
    assert sim.constraint_free and not np.asarray(state.qacc_warmstart).any()
    assert np.asarray(full.qacc_warmstart).any()
    m = sim.mj_model
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = np.asarray(state.qpos), np.asarray(state.qvel)
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(np.asarray(jax.jit(sim.forward)(state).xpos), d.xpos, atol=1e-5)
    with pytest.raises(ValueError, match="forward"):
        CartPoleRobot("effort", "analytic").sim.forward(state)


def test_constraint_free_is_false_where_a_constraint_row_can_exist():
    """Only a model whose constraint solver can never run drops the warm start: contacts on, a joint limit, an
    equality or friction loss each make it keep MJX's value."""
    from jaxrobo.physics.sim import constraint_free

    m = load_model(asset_path("cartpole.xml"))
    assert constraint_free(m)
    for edit in (lambda m: setattr(m.opt, "disableflags", 0),
                 lambda m: m.jnt_limited.__setitem__(0, 1),
                 lambda m: m.dof_frictionloss.__setitem__(0, 0.1)):
        changed = load_model(asset_path("cartpole.xml"))
        edit(changed)
        assert not constraint_free(changed)


# ---- the closed-form backend --------------------------------------------------------------------------------
def test_analytic_backend_matches_native_mujoco_to_float64_roundoff(x64_errors):
    for control_type in ("velocity", "position", "effort"):
        err, swing = x64_errors[("analytic", control_type)]
        assert swing > 1.0, f"{control_type}: the pole should fall and swing"
        assert err < 1e-9, f"{control_type}: analytic and native MuJoCo differ by {err} over 500 steps"


def test_analytic_backend_tracks_mjx_in_float32():
    """Same task, same actions: the two backends stay within float32 round-off over a 2 s episode."""
    import jaxrobo

    traces = []
    for backend in ("mjx", "analytic"):
        env = jaxrobo.make("CartPoleStayUp-v0", backend=backend, init_noise=0.0, init_pole_angle=0.05)
        step = jax.jit(env.step)
        state, obs = env.reset(jax.random.key(0)), []
        for t in range(50):
            state = step(state, (0, 1, 1, 0, 3)[t % 5])
            obs.append(np.asarray(state.obs))
        traces.append(np.array(obs))
    assert np.abs(traces[0][:, 2]).max() > 0.1, "the pole should move"
    np.testing.assert_allclose(traces[1], traces[0], atol=2e-4)


@pytest.mark.parametrize("control_type", ["velocity", "position", "effort"])
def test_the_kernels_coordinate_step_is_the_physics_step(control_type):
    """``CartPoleSim.coordinate_step`` (what the Pallas chunk kernel runs on its ``[block]`` vectors) and
    ``physics_step`` (the XLA path, on stacked coordinates) are one set of equations: 256 random states and
    controls, one step, equal bit for bit op by op and compiled, and with the kernel's own ``sin``/``cos``
    passed in, those are the ones used."""
    sim = CartPoleRobot(control_type, "analytic", running_step=0.01, timestep=0.01).sim
    k = jax.random.split(jax.random.key(0), 3)
    q = jax.random.uniform(k[0], (256, 2), minval=-1.5, maxval=1.5)
    v = jax.random.uniform(k[1], (256, 2), minval=-3.0, maxval=3.0)
    u = jax.random.uniform(k[2], (256, 1), minval=-2.0, maxval=2.0)
    stacked = lambda q, v, u: jax.vmap(sim.physics_step)(JointState(q, v), u)  # noqa: E731
    columns = lambda q, v, u, sincos=None: sim.coordinate_step(  # noqa: E731
        q[:, 0], q[:, 1], v[:, 0], v[:, 1], (u[:, 0],), sincos)
    with jax.disable_jit():
        runs = [(stacked(q, v, u), columns(q, v, u))]
    runs.append((jax.jit(stacked)(q, v, u), jax.jit(columns)(q, v, u)))
    for xla, coords in runs:
        for got, want in zip(coords, (xla.qpos[:, 0], xla.qpos[:, 1], xla.qvel[:, 0], xla.qvel[:, 1])):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    crude = columns(q, v, u, lambda th: (th, 1.0 - 0.5 * th * th))  # small-angle sin/cos: other values
    assert not np.array_equal(np.asarray(crude[2]), np.asarray(runs[1][0].qvel[:, 0]))


def test_analytic_backend_refuses_what_it_cannot_model():
    from envs.cartpole.robot import CART_JOINT, MJCF, POLE_JOINT
    from envs.cartpole.dynamics import CartPoleSim

    with pytest.raises(ValueError, match="damping"):
        CartPoleSim(load_model(asset_path(MJCF), edit=lambda s: setattr(s.joint(CART_JOINT), "damping", [0.5, 0, 0])),
                    CART_JOINT, POLE_JOINT)
    with pytest.raises(ValueError, match="limits"):
        CartPoleSim(load_model(asset_path(MJCF), edit=lambda s: setattr(s.joint(POLE_JOINT), "range", [-1, 1])),
                    CART_JOINT, POLE_JOINT)
    with pytest.raises(ValueError, match="backend='mjx'"):
        CartPoleSim(load_model(asset_path(MJCF)), CART_JOINT, "no_such_joint")


def test_analytic_backend_is_a_task_option():
    import jaxrobo

    env = jaxrobo.make("CartPoleStayUp-v0", backend="analytic")
    assert env.robot.sim.backend == "analytic" and env.robot.sim.n_substeps == 4
    with pytest.raises(Exception, match="backend"):
        jaxrobo.make("CartPoleStayUp-v0", backend="bullet")
