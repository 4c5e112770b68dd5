"""The quadcopter robot: on-board controller behaviour, the rigid backend against MJX, and the exact geometry
(sonar rays, crash spheres) against brute force. Tasks are in ``test_quadcopter_tasks.py``."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from envs.quadcopter.geometry import BOX, CYLINDER
from envs.quadcopter.robot import (ControllerGains, Obstacles, Quadcopter, point_obstacle_distance, ray_box,
                                   ray_cylinder, ray_ground, sonar, sphere_hits, twist_command)

SPEED = 1.0
MAX_INCL = 0.7
DT = 0.01


@pytest.fixture(scope="module")
def rigid():
    """The rigid-backend robot and a jitted fly(command sequence [T,4] per physics step) -> per-step readings."""
    robot = Quadcopter("rigid", running_step=0.3)
    return robot, _flyer(robot)


HORIZON = 1000  # every flight is 10 s of physics steps, so one compiled function serves all tests


def _flyer(robot):
    def fly(qpos, qvel, commands):
        def body(s, cmd):
            ctrl = robot.controller(s, cmd)
            s = robot.sim.physics_step(s, ctrl)
            r = robot.read_sensors(s)
            return s, (r["pos"], r["rpy"], r["vel_heading"], r["omega"], ctrl)

        return jax.lax.scan(body, robot.sim.init(qpos, qvel), commands)[1]

    fly = jax.jit(fly)

    def padded(qpos, qvel, commands):
        n = commands.shape[0]
        assert n <= HORIZON
        full = jnp.zeros((HORIZON, 4)).at[:n].set(commands)
        return [x[:n] for x in fly(qpos, qvel, full)]

    return padded


def _hold(action: int, seconds: float) -> jax.Array:
    return jnp.tile(twist_command(jnp.int32(action), SPEED)[None], (int(round(seconds / DT)), 1))


# ---- controller --------------------------------------------------------------------------------------------
def test_hover_holds_altitude_10s(rigid):
    robot, fly = rigid
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]), 0.3)
    pos, *_ = fly(qpos, qvel, jnp.zeros((1000, 4)))  # 10 s of zero Twist
    assert float(jnp.max(jnp.abs(pos[:, 2] - 1.0))) < 0.05
    assert float(jnp.max(jnp.linalg.norm(pos[:, :2], axis=1))) < 0.05


def test_hover_from_disturbed_state_recovers(rigid):
    """Hover holds altitude within 5 cm for 10 s even after a kick (tilted, moving)."""
    robot, fly = rigid
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]))
    qvel = qvel.at[:6].set(jnp.array([0.3, -0.2, 0.0, 0.5, -0.5, 0.2]))
    pos, rpy, vel, *_ = fly(qpos, qvel, jnp.zeros((1000, 4)))
    assert float(jnp.max(jnp.abs(pos[:, 2] - 1.0))) < 0.05
    assert float(jnp.max(jnp.abs(vel[-100:]))) < 0.02


def test_forward_reaches_90_percent_within_1s(rigid):
    robot, fly = rigid
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]), 1.0)
    _, _, vel, *_ = fly(qpos, qvel, _hold(0, 1.0))
    assert float(vel[-1, 0]) >= 0.9 * SPEED
    first = int(np.argmax(np.asarray(vel[:, 0]) >= 0.9 * SPEED))
    assert (first + 1) * DT <= 1.0


@pytest.mark.parametrize("action,axis,sign", [(3, 2, 1.0), (4, 2, -1.0)])
def test_up_down(rigid, action, axis, sign):
    robot, fly = rigid
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 2.0]))
    pos, _, vel, *_ = fly(qpos, qvel, _hold(action, 1.5))
    assert sign * float(vel[-1, 2]) >= 0.9 * SPEED
    assert sign * float(pos[-1, 2] - 2.0) > 0.8
    assert float(jnp.max(jnp.linalg.norm(pos[:, :2], axis=1))) < 0.05  # straight up/down


@pytest.mark.parametrize("action,sign", [(1, 1.0), (2, -1.0)])
def test_turns(rigid, action, sign):
    robot, fly = rigid
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]))
    pos, rpy, vel, omega, _ = fly(qpos, qvel, _hold(action, 1.0))
    assert sign * float(omega[-1, 2]) >= 0.9 * SPEED
    assert sign * float(rpy[-1, 2]) > 0.6  # turned about 0.9 rad in 1 s
    assert abs(float(pos[-1, 2] - 1.0)) < 0.05
    assert abs(float(vel[-1, 0]) - 0.05) < 0.02  # the seed's creep forward while turning


def test_attitude_and_rotor_limits_for_every_action(rigid):
    """Every action, and abrupt switches between them, keep roll/pitch under max_incl and rotors in range."""
    robot, fly = rigid
    seq = jax.random.randint(jax.random.key(0), (40,), 0, 5)
    per_step = jnp.repeat(jax.vmap(lambda a: twist_command(a, SPEED))(seq), 30, axis=0)
    singles = jnp.concatenate([_hold(a, 1.0) for a in range(5)] + [per_step[:500]])
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 5.0]))
    _, rpy, _, _, ctrl = fly(qpos, qvel, singles)
    assert float(jnp.max(jnp.abs(rpy[:, :2]))) < MAX_INCL
    assert float(jnp.max(jnp.abs(rpy[:, :2]))) <= ControllerGains().max_tilt + 0.05
    assert float(jnp.min(ctrl)) >= min(robot.control.ctrl_low) and float(jnp.max(ctrl)) <= max(robot.control.ctrl_high)


def test_controller_output_in_limits_from_wild_states(rigid):
    robot, _ = rigid
    k = jax.random.split(jax.random.key(1), 3)
    quat = jax.random.normal(k[0], (256, 4))
    quat = quat / jnp.linalg.norm(quat, axis=1, keepdims=True)
    qpos = jnp.concatenate([jnp.ones((256, 3)), quat], axis=1)
    qvel = 5 * jax.random.normal(k[1], (256, 6))
    cmd = 3 * jax.random.normal(k[2], (256, 4))
    ctrl = jax.vmap(lambda q, v, c: robot.controller(robot.sim.init(q, v), c))(qpos, qvel, cmd)
    assert bool(jnp.all(ctrl >= 0.0)) and bool(jnp.all(ctrl <= 2.0))


def test_altitude_floor_stops_descent():
    robot = Quadcopter("rigid", running_step=0.3, min_altitude=0.3)
    fly = _flyer(robot)
    qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]))
    pos, *_ = fly(qpos, qvel, _hold(4, 4.0))
    assert float(jnp.min(pos[:, 2])) > 0.2 and abs(float(pos[-1, 2]) - 0.3) < 0.05


def test_rigid_backend_matches_mjx():
    """Same model, same controller: the hand-written backend tracks MJX within 1 mm / 1 mrad over 6 s."""
    seq = jnp.array([0, 0, 1, 1, 0, 3, 0, 2, 2, 4, 0, 0, 1, 3, 0, 4, 2, 0, 0, 1])  # 20 control steps of 0.3 s
    traj = {}
    for backend in ("rigid", "mjx"):
        robot = Quadcopter(backend, running_step=0.3)
        qpos, qvel = robot.init_pose(jnp.array([0.0, 0.0, 1.0]), 0.2)

        def run(s, a, robot=robot):
            s = robot.advance(s, twist_command(a, SPEED))
            r = robot.read_sensors(s)
            return s, jnp.concatenate([r["pos"], r["quat"], r["vel"], r["omega"]])

        traj[backend] = np.asarray(jax.jit(lambda s, seq: jax.lax.scan(run, s, seq)[1])(robot.sim.init(qpos, qvel),
                                                                                           seq))
    diff = np.abs(traj["rigid"] - traj["mjx"])
    assert diff[:, :3].max() < 1e-3, diff[:, :3].max()  # position, m
    assert diff[:, 3:7].max() < 1e-3  # quaternion
    assert diff[:, 7:].max() < 1e-2  # velocities
    assert np.abs(traj["rigid"][-1, :3]).max() > 1.0  # it did fly somewhere


# ---- geometry against brute force --------------------------------------------------------------------------
def _inside_box(p, c, h):
    return np.all(np.abs(p - c) <= h, axis=-1)


def _inside_cyl(p, c, r, hh):
    return (np.sum((p[..., :2] - c[:2]) ** 2, axis=-1) <= r * r) & (np.abs(p[..., 2] - c[2]) <= hh)


def _check_first_hit(t, origin, d, inside, surface_dist, max_t=8.0, step=2e-3):
    """``t`` is the exact first hit: every sampled point before it is outside, the hit point is on the surface,
    and if brute force finds an inside point, ``t`` is no later than it."""
    s = np.arange(0.0, max_t, step)
    pts = origin + s[:, None] * d
    ins = inside(pts)
    brute = s[np.argmax(ins)] if ins.any() else None
    if t >= 1e5:  # miss
        assert brute is None, brute
        return
    if t > 0:
        assert surface_dist(origin + t * d) < 1e-3
    assert not np.any(ins[s < t - step]), "a point before the reported hit is inside"
    if brute is not None:
        assert t <= brute + step


_ray_box, _ray_cylinder, _ray_ground = jax.jit(ray_box), jax.jit(ray_cylinder), jax.jit(ray_ground)
_point_distance, _sphere_hits = jax.jit(point_obstacle_distance), jax.jit(sphere_hits)
vec = st.tuples(*[st.floats(-3, 3, allow_nan=False)] * 3)
direction = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2)
positive = st.tuples(*[st.floats(0.1, 1.5, allow_nan=False)] * 3)


@settings(max_examples=40, deadline=None)
@given(vec, direction, vec, positive)
@example((0.0, 1.0, 1.0), (0.0, 0.0, -1.0), (0.0, 0.0, -1.0), (1.0, 1.0, 1.0))  # grazing down the face y = 1
def test_ray_box_vs_brute_force(origin, d, center, half):
    o, c, h = (np.asarray(x, np.float32) for x in (origin, center, half))
    d = np.asarray(d, np.float32) / np.linalg.norm(d)
    t = float(_ray_box(jnp.asarray(o), jnp.asarray(d), jnp.asarray(c), jnp.asarray(h)))
    surf = lambda p: float(np.abs(np.max(np.abs(p - c) - h)))  # noqa: E731 (0 on the surface)
    _check_first_hit(t, o, d, lambda p: _inside_box(p, c, h), surf)


@settings(max_examples=40, deadline=None)
@given(vec, direction, vec, positive)
def test_ray_cylinder_vs_brute_force(origin, d, center, size):
    o, c = np.asarray(origin, np.float32), np.asarray(center, np.float32)
    d = np.asarray(d, np.float32) / np.linalg.norm(d)
    r, hh = np.float32(size[0]), np.float32(size[2])
    t = float(_ray_cylinder(jnp.asarray(o), jnp.asarray(d), jnp.asarray(c), jnp.float32(r), jnp.float32(hh)))

    def surf(p):
        radial = np.linalg.norm(p[:2] - c[:2]) - r
        vertical = abs(p[2] - c[2]) - hh
        return abs(max(radial, vertical)) if max(radial, vertical) >= -1e-3 else 1.0

    _check_first_hit(t, o, d, lambda p: _inside_cyl(p, c, r, hh), surf)


@settings(max_examples=30, deadline=None)
@given(vec, direction)
def test_ray_ground_vs_brute_force(origin, d):
    o = np.asarray(origin, np.float32) + np.float32([0, 0, 3.1])  # above the ground
    d = np.asarray(d, np.float32) / np.linalg.norm(d)
    t = float(_ray_ground(jnp.asarray(o), jnp.asarray(d)))
    _check_first_hit(t, o, d, lambda p: p[..., 2] <= 0, lambda p: abs(float(p[2])), max_t=20.0)


def _grid_points_box(c, h, n=24):
    axes = [np.linspace(c[i] - h[i], c[i] + h[i], n) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), np.max(2 * h / (n - 1))


def _grid_points_cyl(c, r, hh, n=24):
    rad, ang, z = np.linspace(0, r, n), np.linspace(0, 2 * np.pi, 4 * n), np.linspace(c[2] - hh, c[2] + hh, n)
    R, A, Z = np.meshgrid(rad, ang, z, indexing="ij")
    pts = np.stack([c[0] + R * np.cos(A), c[1] + R * np.sin(A), Z], -1).reshape(-1, 3)
    return pts, max(r / (n - 1), r * 2 * np.pi / (4 * n), 2 * hh / (n - 1))


@settings(max_examples=30, deadline=None)
@given(vec, vec, positive, st.booleans(), st.floats(0.05, 0.5))
def test_crash_sphere_vs_brute_force(point, center, size, is_box, radius):
    p, c, s = (np.asarray(x, np.float64) for x in (point, center, size))
    obs = Obstacles(jnp.array([BOX if is_box else CYLINDER]), jnp.asarray(c[None], jnp.float32),
                    jnp.asarray(s[None], jnp.float32), jnp.array([True]))
    exact = float(_point_distance(jnp.asarray(p, jnp.float32), obs))
    pts, spacing = _grid_points_box(c, s) if is_box else _grid_points_cyl(c, s[0], s[2])
    brute = float(np.min(np.linalg.norm(pts - p, axis=1)))
    assert exact <= brute + 1e-4
    assert brute - exact <= spacing * np.sqrt(3) + 1e-4
    ground, hit = _sphere_hits(jnp.asarray(p, jnp.float32), jnp.float32(radius), obs)
    if abs(brute - radius) > spacing * 2:  # away from the boundary the two agree on "crashed"
        assert bool(hit) == (brute <= radius)
    assert bool(ground) == (p[2] <= radius)


def test_sonar_sees_obstacle_ahead_and_ground_below():
    obs = Obstacles(jnp.array([CYLINDER, BOX]), jnp.array([[3.0, 0.0, 1.5], [0.0, 2.5, 1.5]]),
                    jnp.array([[0.5, 0.5, 1.5], [0.5, 0.5, 1.5]]), jnp.array([True, True]))
    quat = jnp.array([1.0, 0.0, 0.0, 0.0])
    ranges = sonar(jnp.array([0.0, 0.0, 1.0]), quat, obs, 4.0)
    np.testing.assert_allclose(np.asarray(ranges), [2.5, 4.0, 4.0, 1.0], atol=1e-5)
    ranges = sonar(jnp.array([0.0, 0.0, 1.0]), jnp.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]), obs, 4.0)
    assert abs(float(ranges[0]) - 2.0) < 1e-5  # turned left 90 deg: the box face at y = 2
    inactive = obs.replace(active=jnp.array([False, False]))
    assert float(sonar(jnp.array([0.0, 0.0, 1.0]), quat, inactive, 4.0)[0]) == 4.0


def test_controller_on_python_floats_is_numpys_float64():
    """The native port runs the controller on Python floats (``FLOATS``): numpy's float64 values on the same
    states to float64 round-off (numpy's vector atan2/asin are another implementation), and the float32 JAX
    controller's to its round-off."""
    from envs.quadcopter.dynamics import controller
    from jaxrobo.core.scalar import FLOATS

    robot = Quadcopter("rigid", running_step=0.3, min_altitude=0.3)
    rs = np.random.default_rng(0)
    q = np.concatenate([rs.uniform(-2, 2, (64, 3)), rs.normal(size=(64, 4))], axis=1)
    q[:, 3:] /= np.linalg.norm(q[:, 3:], axis=1, keepdims=True)
    v, cmd = rs.normal(size=(64, 6)), rs.uniform(-1, 1, (64, 4))
    vector = np.stack(controller(np, robot.control, list(q.T), list(v.T), list(cmd.T)), axis=1)
    scalar = np.array([controller(FLOATS, robot.control, qi.tolist(), vi.tolist(), ci.tolist())
                       for qi, vi, ci in zip(q, v, cmd)])
    assert scalar.dtype == np.float64
    np.testing.assert_allclose(scalar, vector, rtol=1e-13, atol=1e-13)
    f32 = np.stack(controller(jnp, robot.control, list(jnp.asarray(q.T, jnp.float32)),
                              list(jnp.asarray(v.T, jnp.float32)), list(jnp.asarray(cmd.T, jnp.float32))), axis=1)
    np.testing.assert_allclose(f32, vector, rtol=1e-4, atol=1e-4)
