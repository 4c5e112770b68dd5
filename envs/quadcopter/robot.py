"""The quadcopter robot (the seed's Parrot AR.Drone robot env): model, on-board controller, pose and sonar.

* **Model** - ``envs/quadcopter/quadcopter.xml``: a 0.42 kg X-quadrotor on a free joint, four site-thrust actuators each
  with its reaction yaw torque, contacts disabled (crashes are exact geometry, see :func:`sphere_hits`).
* **Backends** - ``mjx`` (MuJoCo MJX) or ``rigid`` (:mod:`envs.quadcopter.rigid_body`: Newton–Euler for the one free
  body, every constant read from the same compiled model; agrees with MJX to round-off and is much faster). On ``rigid``
  the robot also offers its control step as a Pallas kernel (:mod:`envs.quadcopter.kernel`), which
  ``ExecutionPlan(fused="pallas")`` runs.
* **On-board controller** (:meth:`Quadcopter.controller`, every physics substep, on every backend; its equations
  are :func:`envs.quadcopter.dynamics.controller`, which the Pallas kernels run too) - the seed's ``cmd_vel`` Twist
  ``[vx, vy, vz, yaw_rate]`` in the heading frame (body frame with roll and pitch removed) is tracked by a
  cascade: velocity error → desired acceleration (tilt-limited) → desired roll/pitch and collective thrust →
  attitude PD and yaw-rate P → torques → rotor thrusts through the inverse of the model's mixing matrix,
  clipped to the motor limits. An optional altitude floor (``min_altitude``) makes descent commands stop above
  the ground, as the AR.Drone's sonar-based firmware does; with it at 0 the drone can fly into the ground.
* **Sensors** - :meth:`Quadcopter.read_sensors`: position, roll/pitch/yaw, world and heading-frame velocity,
  body rates. :func:`sonar`: ranges along fixed body rays to the ground and to obstacles (axis-aligned boxes
  and vertical cylinders held as task data in :class:`Obstacles`), by exact ray–shape tests. The geometry is
  :mod:`envs.quadcopter.geometry`'s, written once per coordinate for the hooks, the Pallas kernel and the
  native port; the functions here apply it to arrays of 3 coordinates.
"""
from __future__ import annotations

import os
import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter import dynamics, geometry, goto_step
from envs.quadcopter.geometry import INF, SONAR_RAYS
from envs.quadcopter.goto_step import ACTION_NAMES, twist
from envs.quadcopter.rigid_body import RigidBodySim, airframe_from_model
from jaxrobo.api import (MjxEdit, Robot, TaskEnv, backend_choices, load_model, make_simulator, param, pytree_dataclass,
                         randomise, spaces)

#: The robot's MJCF, beside this module.
MJCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "quadcopter.xml")
#: The quadcopter's hand-written backend; of the engines, its tasks offer MJX only.
CLOSED_FORM = {"rigid": RigidBodySim}
ENGINES = ("mjx",)
BACKENDS = backend_choices(CLOSED_FORM, ENGINES)
SONAR_NAMES = ("forward", "left", "right", "down")
def twist_command(action: jax.Array, speed_value: jax.Array) -> jax.Array:
    """The seed's Twist for an action index (0 forward, 1 left, 2 right, 3 up, 4 down) at ``speed_value``
    (:func:`envs.quadcopter.goto_step.twist`)."""
    return jnp.stack(twist(jnp, action, speed_value))


@dataclasses.dataclass(frozen=True)
class ControllerGains:
    """Gains and limits of the on-board cascade (static: baked into the compiled step)."""

    k_vel_xy: float = 3.5  # 1/s: horizontal velocity error → acceleration
    k_vel_z: float = 4.0  # 1/s: vertical velocity error → acceleration
    max_tilt: float = 0.35  # rad: roll/pitch set-points are limited to this (below the task's max_incl)
    max_acc_up: float = 6.0  # m/s^2 above gravity compensation
    max_acc_down: float = 5.0  # m/s^2 below it
    k_att: float = 144.0  # 1/s^2: attitude stiffness (natural frequency 12 rad/s)
    k_rate: float = 20.0  # 1/s: attitude damping
    k_yaw: float = 8.0  # 1/s: yaw-rate error → yaw acceleration
    k_floor: float = 2.0  # 1/s: altitude-floor climb rate per m below the floor


@pytree_dataclass
class Obstacles:
    """Obstacles as task data, ``[n]`` each: ``kind`` (0 box, 1 vertical cylinder), ``center`` [n, 3] (m),
    ``size`` [n, 3] (box: half extents; cylinder: radius, unused, half height), ``active`` (False: ignored)."""

    kind: jax.Array
    center: jax.Array
    size: jax.Array
    active: jax.Array

    @staticmethod
    def empty() -> "Obstacles":
        return Obstacles(jnp.zeros(0, jnp.int32), jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros(0, bool))


# ---- pose helpers ----------------------------------------------------------------------------------------
def euler_from_quat(q: jax.Array) -> jax.Array:
    """``[roll, pitch, yaw]`` (rad) of a wxyz quaternion, ZYX convention (:func:`envs.quadcopter.geometry.euler`)."""
    return jnp.stack(geometry.euler(jnp, q[0], q[1], q[2], q[3]))


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix (body → world) of a unit wxyz quaternion."""
    return jnp.array(dynamics.rotation(q[0], q[1], q[2], q[3]))


def quat_from_yaw(yaw: jax.Array) -> jax.Array:
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(yaw / 2)])


# ---- exact geometry (envs.quadcopter.geometry, on arrays of 3 coordinates) ---------------------------------
def _xyz(a: jax.Array) -> list:
    return [a[..., i] for i in range(3)]


def ray_ground(origin: jax.Array, direction: jax.Array) -> jax.Array:
    """Distance along a unit ray to the plane z = 0 (``INF`` if it points up or sideways; 0 if below it)."""
    return geometry.ray_ground(jnp, _xyz(origin), _xyz(direction))


def ray_box(origin: jax.Array, direction: jax.Array, center: jax.Array, half: jax.Array) -> jax.Array:
    """Slab test: distance to an axis-aligned box (0 when the origin is inside, ``INF`` on a miss)."""
    return geometry.ray_box(jnp, _xyz(origin), _xyz(direction), _xyz(center), _xyz(half))


def ray_cylinder(origin: jax.Array, direction: jax.Array, center: jax.Array, radius: jax.Array,
                 half_height: jax.Array) -> jax.Array:
    """Distance to a vertical solid cylinder: side wall, both caps, or 0 from inside; ``INF`` on a miss."""
    return geometry.ray_cylinder(jnp, _xyz(origin), _xyz(direction), _xyz(center), radius, half_height)


#: Both kinds, chosen per obstacle by its ``kind``.
KINDS = goto_step.kinds_of("mixed")


def fold_obstacles(obstacles: "Obstacles", distances: Callable[..., tuple], init: tuple | None = None) -> tuple:
    """The elementwise minimum over the active obstacles of ``distances(kind, center [3], size [3], active)`` (an
    iterable; ``INF`` where inactive): vmapped over the obstacle arrays (``init`` where there are none). The Goto
    hooks' fold (:func:`envs.quadcopter.goto_step.observe`)."""
    if obstacles.kind.shape[0] == 0:
        return (jnp.asarray(INF, jnp.float32),) if init is None else init

    def one(kind, center, size, active):
        return tuple(distances(kind, _xyz(center), _xyz(size), active))

    return tuple(jnp.min(t, axis=0) for t in jax.vmap(one)(obstacles.kind, obstacles.center, obstacles.size,
                                                             obstacles.active))


def ray_obstacles(origin: jax.Array, direction: jax.Array, obstacles: Obstacles) -> jax.Array:
    """Distance along a unit ray to the nearest active obstacle (``INF`` if none)."""
    return fold_obstacles(obstacles, lambda *obstacle: goto_step.obstacle_distances(
        jnp, _xyz(origin), [_xyz(direction)], KINDS, *obstacle))[0]


def sonar(pos: jax.Array, quat: jax.Array, obstacles: Obstacles, max_range: float | jax.Array,
          rays: np.ndarray = SONAR_RAYS) -> jax.Array:
    """Range (m) along each body-frame ray to the ground or an obstacle, clipped to ``max_range``."""
    # The rays rotated with the products written out (dynamics' order), not as a batched matrix product, whose
    # algorithm (and so its rounding) XLA chooses by the batch's shape (on a GPU by autotuning): an env's ranges
    # must not depend on how many envs, or devices, step together.
    rot = dynamics.rotation(quat[0], quat[1], quat[2], quat[3])
    dirs = jnp.stack([jnp.stack([dynamics._dot(ray, row) for row in rot]) for ray in np.asarray(rays, np.float32)])

    def one(d):
        return jnp.minimum(ray_ground(pos, d), ray_obstacles(pos, d, obstacles))

    return jnp.minimum(jax.vmap(one)(dirs), max_range)


def point_obstacle_distance(p: jax.Array, obstacles: Obstacles) -> jax.Array:
    """Euclidean distance from a point to the nearest active obstacle surface (0 inside; ``INF`` if none)."""
    return fold_obstacles(obstacles, lambda *obstacle: goto_step.obstacle_distances(
        jnp, _xyz(p), [], KINDS, *obstacle))[0]


def sphere_hits(pos: jax.Array, radius: float | jax.Array, obstacles: Obstacles) -> tuple[jax.Array, jax.Array]:
    """Exact crash test of the drone as a sphere: ``(hits_ground, hits_obstacle)``."""
    return pos[2] <= radius, point_obstacle_distance(pos, obstacles) <= radius


# ---- the robot -------------------------------------------------------------------------------------------
class Quadcopter(Robot):
    """The AR.Drone-like quadrotor; the command is the seed's Twist ``[vx, vy, vz, yaw_rate]`` (m/s, rad/s)."""

    def __init__(self, backend: str = "mjx", running_step: float = 0.3, timestep: float = 0.01,
                 min_altitude: float = 0.0, gains: ControllerGains = ControllerGains()):
        mj_model = load_model(MJCF, timestep=timestep)
        physics = lambda: load_model(MJCF, timestep=timestep, physics_only=True)  # noqa: E731
        super().__init__(make_simulator(mj_model, backend, running_step, physics, closed_form=CLOSED_FORM,
                                        engines=ENGINES))
        self.gains = gains
        self.min_altitude = float(min_altitude)
        af = airframe_from_model(mj_model)  # constants of the controller, from the same model as the physics
        self.control = dynamics.controller_constants(af, gains, self.min_altitude)
        self.hover_thrust = af.mass * self.control.g / af.wrench[2].sum()
        self._body = int(mj_model.nbody - 1)  # the drone: the one body after the world
        if backend == "rigid":  # the control step as one Pallas kernel, for ExecutionPlan(fused="pallas")
            from envs.quadcopter.kernel import make_advance

            self.advance_kernel = make_advance(self)

    #: A wind is a horizontal force: its direction is drawn beside its magnitude.
    directional = ("wind",)

    def randomisable(self) -> tuple[str, ...]:
        """``mass`` (a factor on the airframe's mass and inertia: the same shape, heavier or lighter),
        ``motor_gain`` (a factor on every rotor's thrust and reaction torque per unit control) and ``wind`` (a
        constant horizontal force on the body, N, in a random direction), on both backends. The on-board
        controller keeps the nominal values, as a real one would."""
        return ("mass", "motor_gain", "wind")

    def sim_physics(self, domain: dict[str, jax.Array]) -> Any:
        """A drawn domain as the backend's physics: the rigid body's factors and force, or MJX model and data fields."""
        one = jnp.ones((), jnp.float32)
        mass, gain = domain.get("mass", one), domain.get("motor_gain", one)
        wind = domain.get("wind", 0.0 * one)
        heading = domain.get("wind" + randomise.HEADING, 0.0 * one)
        force = jnp.stack([wind * jnp.cos(heading), wind * jnp.sin(heading), 0.0 * wind])
        if self.sim.backend == "rigid":
            return {"mass": mass, "motor_gain": gain, "wind": force}
        m, b = self.sim.model, self._body
        return MjxEdit(
            model={"body_mass": m.body_mass.at[b].multiply(mass), "body_inertia": m.body_inertia.at[b].multiply(mass),
                   "actuator_gainprm": m.actuator_gainprm.at[:, 0].multiply(gain)},
            data={"xfrc_applied": jnp.zeros((self.sim.mj_model.nbody, 6), jnp.float32).at[b, :3].set(force)})

    def init_pose(self, pos: jax.Array, yaw: jax.Array = 0.0) -> tuple[jax.Array, jax.Array]:
        """``(qpos, qvel)`` hovering at rest at ``pos`` (m) with heading ``yaw`` (rad)."""
        qpos = jnp.concatenate([jnp.asarray(pos, jnp.float32), quat_from_yaw(jnp.asarray(yaw, jnp.float32))])
        return qpos, jnp.zeros(6, jnp.float32)

    def controller(self, pipeline_state: Any, command: jax.Array) -> jax.Array:
        """Twist → rotor thrusts (N): the on-board velocity → attitude/thrust → mixing cascade
        (:func:`envs.quadcopter.dynamics.controller`, on the state split into its coordinates)."""
        q, v = self.sim.qpos(pipeline_state), self.sim.qvel(pipeline_state)
        rotors = dynamics.controller(jnp, self.control, [q[..., i] for i in range(7)], [v[..., i] for i in range(6)],
                            [command[..., j] for j in range(4)])
        return jnp.stack(rotors, axis=-1)

    def read_sensors(self, pipeline_state: Any) -> dict[str, jax.Array]:
        """Pose and velocities: ``pos`` (m), ``quat`` (wxyz), ``rpy`` (rad), ``vel`` (world, m/s),
        ``vel_heading`` (heading frame, m/s), ``omega`` (body rates, rad/s)."""
        q, v = self.sim.qpos(pipeline_state), self.sim.qvel(pipeline_state)
        rpy = euler_from_quat(q[3:7])
        c, s = jnp.cos(rpy[2]), jnp.sin(rpy[2])
        vel_heading = jnp.stack([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])
        return {"pos": q[:3], "quat": q[3:7], "rpy": rpy, "vel": v[:3], "vel_heading": vel_heading,
                "omega": v[3:6]}


@pytree_dataclass
class QuadcopterOptions:
    """Static options every quadcopter task has (tasks subclass it to add theirs or change defaults)."""

    backend: str = param("rigid", choices=BACKENDS, static=True,
                         doc="physics: 'mjx' (MuJoCo MJX) or 'rigid' (same model, hand-written one-body dynamics)")
    running_step: float = param(0.3, low=0.0, low_open=True, high=5.0, static=True, unit="s",
                                doc="how long each command is applied")
    timestep: float = param(0.01, low=0.0, low_open=True, high=0.02, static=True, unit="s", doc="physics step")
    min_altitude: float = param(0.0, low=0.0, high=2.0, static=True, unit="m",
                                doc="on-board altitude floor of descent commands (0: none, ground crashes possible)")
    randomise: bool = param(False, static=True,
                            doc="domain randomisation: draw the physics (the task's rand_* ranges) at every reset; "
                                "the Pallas kernels take each env's draw as per-env inputs")


class QuadcopterTask(TaskEnv):
    """What the quadcopter tasks share: the robot built from the task's options (``backend``, ``running_step``,
    ``timestep``, ``min_altitude``) and the seed's five Twist actions."""

    def __init__(self, options: Any = None, params: Any = None):
        super().__init__(options, params)
        o = self.options
        self.robot = Quadcopter(o.backend, o.running_step, o.timestep, min_altitude=o.min_altitude)
        randomise.check(self)

    def action_space(self, params: Any = None) -> spaces.Discrete:
        return spaces.Discrete(len(ACTION_NAMES))
