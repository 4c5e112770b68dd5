"""The quadcopter's equations, written once: its on-board controller and its rigid-body physics, per coordinate.

Every path that flies the quadcopter runs these two functions: :meth:`envs.quadcopter.robot.Quadcopter.controller`
(on every backend, MJX included) calls :func:`controller`, :meth:`envs.quadcopter.rigid_body.RigidBodySim.physics_step`
calls :func:`physics_step`, each on one env's state split into coordinates and stacked back, the Pallas kernels
(:mod:`envs.quadcopter.kernel`, :mod:`envs.quadcopter.goto_kernel`) call both on ``[block]`` vectors, and the
native-MuJoCo port (:mod:`envs.quadcopter.native`) runs :func:`controller` in float64 numpy before every
``mj_step``. They are written per coordinate, over lists of scalars or same-shape arrays, because a Pallas kernel
holds a state as one vector per coordinate (its Triton lowering has no slice or gather within a block); under
``vmap`` the same code runs on one env's scalars. The array module is the caller's (``xp``: ``jax.numpy`` or
``numpy``): this module imports no JAX, so the native port runs without it.

The form chosen is the one that costs a GPU fewest instructions, as the kernel is the default there: the
controller takes the heading's cosine and sine and the cosines of roll and pitch from the quaternion algebraically
instead of through the angles (``cos(atan2(y, x)) = x / hypot(x, y)``, ``cos(asin(s)) = sqrt(1 - s²)``: five
transcendental calls fewer per substep), a division by a constant, or by one value several times, is a
multiplication by its reciprocal (a float32 division is a short routine on a GPU, a multiplication one
instruction), and the matrix products are written out, skipping zero weights. The constants are float32 values
held as Python floats (weakly typed in the trace, so they take the state's dtype), in hashable frozen
dataclasses a kernel bakes in: :class:`ControllerConstants` from the robot's gains and airframe,
:class:`BodyConstants` from the simulator's :class:`~envs.quadcopter.rigid_body.Airframe`.

Public surface: :func:`controller`, :func:`physics_step`, :func:`rotation`, :class:`ControllerConstants`
(:func:`controller_constants`), :class:`BodyConstants` (:func:`body_constants`).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from envs.quadcopter.geometry import roll_terms, yaw_terms
from envs.quadcopter.geometry import sin_pitch as geometry_sin_pitch


def _f32(v: Any) -> float:
    """A constant as the float32 it is computed with (a Python float: weakly typed in the trace)."""
    return float(np.float32(v))


def _f32s(values: Any) -> tuple:
    """A host array's values as nested tuples of float32 values."""
    a = np.asarray(values)
    return tuple(_f32s(row) for row in a) if a.ndim > 1 else tuple(_f32(v) for v in a)


@dataclasses.dataclass(frozen=True)
class ControllerConstants:
    """Every number the on-board controller needs (host floats; baked into the trace)."""

    g: float  # m/s², gravity's magnitude
    mass: float  # kg
    inertia: tuple[float, float, float]  # principal moments, body axes (kg m²)
    unmix: tuple[tuple[float, ...], ...]  # [rotor][thrust, roll, pitch, yaw torque]: the mixing matrix's inverse
    ctrl_low: tuple[float, ...]  # motor limits (N)
    ctrl_high: tuple[float, ...]
    k_vel_xy: float
    k_vel_z: float
    max_tilt: float
    a_max: float  # g tan(max_tilt): the horizontal acceleration at the tilt limit
    max_acc_up: float
    max_acc_down: float
    k_att: float
    k_rate: float
    k_yaw: float
    k_floor: float
    min_altitude: float  # m; 0: no altitude floor


def controller_constants(airframe: Any, gains: Any, min_altitude: float) -> ControllerConstants:
    """The controller's constants from an :class:`~envs.quadcopter.rigid_body.Airframe` (mass, inertia, gravity,
    the rotors' wrench map and limits) and :class:`~envs.quadcopter.robot.ControllerGains`."""
    af, k = airframe, gains
    g = float(-af.gravity[2])
    mix = af.wrench[[2, 3, 4, 5], :]  # rows: thrust (body z), roll, pitch, yaw torque per rotor newton
    return ControllerConstants(
        g=g, mass=float(af.mass), inertia=_f32s(af.inertia), unmix=_f32s(np.linalg.inv(mix)),
        ctrl_low=_f32s(af.ctrl_low), ctrl_high=_f32s(af.ctrl_high), k_vel_xy=float(k.k_vel_xy),
        k_vel_z=float(k.k_vel_z), max_tilt=float(k.max_tilt), a_max=_f32(g * np.tan(k.max_tilt)),
        max_acc_up=float(k.max_acc_up), max_acc_down=float(k.max_acc_down), k_att=float(k.k_att),
        k_rate=float(k.k_rate), k_yaw=float(k.k_yaw), k_floor=float(k.k_floor), min_altitude=float(min_altitude))


@dataclasses.dataclass(frozen=True)
class BodyConstants:
    """Every number the rigid-body step needs (host floats; baked into the trace)."""

    dt: float  # s
    ctrl_low: tuple[float, ...]
    ctrl_high: tuple[float, ...]
    wrench: tuple[tuple[float, ...], ...]  # [6][rotor]: body force, torque about the CoM per unit control
    inertia: tuple[float, float, float]  # principal moments, body axes (kg m²)
    mass: float  # kg
    gravity: tuple[float, float, float]  # m/s²


def body_constants(airframe: Any) -> BodyConstants:
    """The rigid-body step's constants from an :class:`~envs.quadcopter.rigid_body.Airframe`."""
    af = airframe
    return BodyConstants(dt=float(af.timestep), ctrl_low=_f32s(af.ctrl_low), ctrl_high=_f32s(af.ctrl_high),
                         wrench=_f32s(af.wrench), inertia=_f32s(af.inertia), mass=float(af.mass),
                         gravity=_f32s(af.gravity))


def _clip(xp: Any, x, low: float, high: float):
    # jnp.clip's order (max with the low bound, then min with the high one), skipping an infinite bound.
    if math.isfinite(low):
        x = xp.maximum(x, low)
    if math.isfinite(high):
        x = xp.minimum(x, high)
    return x


def _dot(row: Sequence[float], xs: Sequence[Any]):
    """``row @ xs`` written out, skipping zero weights (a zero weight times a finite value adds nothing)."""
    terms = [w * x for w, x in zip(row, xs) if w != 0.0]
    if not terms:
        return xs[0] * 0.0
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def rotation(w, x, y, z) -> list[list]:
    """The rotation matrix (body → world) of a unit wxyz quaternion, as rows of coordinates."""
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def controller(xp: Any, c: ControllerConstants, q: Sequence[Any], v: Sequence[Any], cmd: Sequence[Any]) -> list:
    """The on-board cascade: the Twist ``cmd = [vx, vy, vz, yaw_rate]`` in the heading frame → desired
    acceleration (tilt-limited) → desired roll/pitch and collective thrust → attitude PD and yaw-rate P →
    torques → the four rotor thrusts (N) through the inverse mixing matrix, clipped to the motor limits.
    ``q``: 7 position coordinates (position, wxyz quaternion), ``v``: 6 velocity coordinates (world linear
    velocity, body rates), each a scalar or an array of a common shape."""
    quat = q[3], q[4], q[5], q[6]
    roll_y, roll_x = roll_terms(*quat)
    roll = xp.arctan2(roll_y, roll_x)
    sin_pitch = _clip(xp, geometry_sin_pitch(*quat), -1.0, 1.0)
    pitch = xp.arcsin(sin_pitch)
    # The heading's cosine and sine, and cos(roll), cos(pitch), from the atan2/asin arguments instead of through
    # the angles (cos(atan2(y, x)) = x / hypot(x, y), cos(asin(s)) = sqrt(1 - s^2)). The yaw angle itself is not
    # needed.
    yaw_y, yaw_x = yaw_terms(*quat)
    yaw_h = xp.sqrt(yaw_x * yaw_x + yaw_y * yaw_y)
    level = yaw_h > 0  # atan2(0, 0) = 0: heading 0 where the heading is undefined (pitch +-90 degrees)
    inv_h = 1.0 / xp.where(level, yaw_h, 1.0)
    cy, sy = xp.where(level, yaw_x * inv_h, 1.0), xp.where(level, yaw_y * inv_h, 0.0)
    roll_h = xp.sqrt(roll_x * roll_x + roll_y * roll_y)
    cos_roll = xp.where(roll_h > 0, roll_x / xp.where(roll_h > 0, roll_h, 1.0), 1.0)
    cos_pitch = xp.sqrt(xp.maximum(1 - sin_pitch * sin_pitch, 0.0))
    vz_cmd = cmd[2]
    if c.min_altitude > 0:  # the altitude floor: descent commands stop above it
        vz_cmd = xp.maximum(vz_cmd, c.k_floor * (c.min_altitude - q[2]))
    vx_h, vy_h = cy * v[0] + sy * v[1], -sy * v[0] + cy * v[1]
    ax = _clip(xp, c.k_vel_xy * (cmd[0] - vx_h), -c.a_max, c.a_max)
    ay = _clip(xp, c.k_vel_xy * (cmd[1] - vy_h), -c.a_max, c.a_max)
    az = _clip(xp, c.k_vel_z * (vz_cmd - v[2]), -c.max_acc_down, c.max_acc_up)
    pitch_d = _clip(xp, xp.arctan2(ax, c.g + az), -c.max_tilt, c.max_tilt)
    roll_d = _clip(xp, xp.arctan2(-ay, c.g + az), -c.max_tilt, c.max_tilt)
    thrust = c.mass * (c.g + az) / xp.maximum(cos_roll * cos_pitch, 0.5)
    torque = [c.inertia[0] * (c.k_att * (roll_d - roll) - c.k_rate * v[3]),
              c.inertia[1] * (c.k_att * (pitch_d - pitch) - c.k_rate * v[4]),
              c.inertia[2] * (c.k_yaw * (cmd[3] - v[5]))]
    wanted = [thrust] + torque
    return [_clip(xp, _dot(row, wanted), lo, hi) for row, lo, hi in zip(c.unmix, c.ctrl_low, c.ctrl_high)]


def physics_step(xp: Any, c: BodyConstants, q: Sequence[Any], v: Sequence[Any], ctrl: Sequence[Any],
                 physics: dict | None = None) -> tuple[list, list]:
    """One physics step of the free body (MuJoCo's semi-implicit Euler): Newton–Euler under the actuators'
    body-frame wrench and gravity, velocities first, then positions with the new velocities, the quaternion
    rotated by ``omega dt`` about the body axes and renormalised (``mju_quatIntegrate``). ``q``: 7 position
    coordinates (world position, wxyz quaternion), ``v``: 6 velocity coordinates (world linear velocity, body
    rates), ``ctrl``: one value per actuator. ``physics``: one env's drawn domain (domain randomisation,
    :meth:`envs.quadcopter.robot.Quadcopter.sim_physics`: factors ``mass`` on mass and inertia and ``motor_gain``
    on the actuators' wrench, a world-frame force ``wind``, an array whose last axis holds its 3 components or,
    as a kernel holds it, a list of 3 per-coordinate values): traced values, whose reciprocals are taken in the
    trace; the kernels pass each env's domain as per-env inputs of the same names. Returns the new ``(q, v)`` as
    lists."""
    dt = c.dt
    ctrl = [_clip(xp, u, lo, hi) for u, lo, hi in zip(ctrl, c.ctrl_low, c.ctrl_high)]
    wr = [_dot(row, ctrl) for row in c.wrench]
    inertia = c.inertia
    inv_mass = _f32(1.0 / np.float32(c.mass))
    inv_inertia = [_f32(1.0 / np.float32(i)) for i in inertia]
    wind = None
    if physics is not None:
        wr = [w * physics["motor_gain"] for w in wr]
        mass = c.mass * physics["mass"]
        inertia = [i * physics["mass"] for i in inertia]
        inv_mass, inv_inertia = 1.0 / mass, [1.0 / i for i in inertia]
        wind = physics["wind"]
        wind = list(wind) if isinstance(wind, (list, tuple)) else [wind[..., i] for i in range(3)]
    qw, qx, qy, qz = q[3], q[4], q[5], q[6]
    rot = rotation(qw, qx, qy, qz)
    force = wr[:3]
    acc = []
    for i in range(3):
        f = rot[i][0] * force[0] + rot[i][1] * force[1] + rot[i][2] * force[2]
        acc.append(f * inv_mass + c.gravity[i] if wind is None else f * inv_mass + c.gravity[i] + wind[i] * inv_mass)
    om = v[3:6]
    l_mom = [inertia[i] * om[i] for i in range(3)]
    cross = [om[1] * l_mom[2] - om[2] * l_mom[1], om[2] * l_mom[0] - om[0] * l_mom[2],
             om[0] * l_mom[1] - om[1] * l_mom[0]]
    alpha = [(wr[3 + i] - cross[i]) * inv_inertia[i] for i in range(3)]
    vel = [v[i] + dt * acc[i] for i in range(3)]
    om = [om[i] + dt * alpha[i] for i in range(3)]
    pos = [q[i] + dt * vel[i] for i in range(3)]
    # Rotate by omega * dt about the body axes, then renormalise; sin(half)/|omega| written to stay finite (and
    # differentiable) at omega = 0.
    angle = xp.sqrt(om[0] * om[0] + om[1] * om[1] + om[2] * om[2]) * dt
    half = 0.5 * angle
    scale = xp.where(angle > 1e-8, xp.sin(half) / xp.maximum(angle, 1e-8), 0.5 - half * half / 12.0) * dt
    bw, bx, by, bz = xp.cos(half), om[0] * scale, om[1] * scale, om[2] * scale
    out = [qw * bw - qx * bx - qy * by - qz * bz, qw * bx + qx * bw + qy * bz - qz * by,
           qw * by - qx * bz + qy * bw + qz * bx, qw * bz + qx * by - qy * bx + qz * bw]
    inv_norm = 1.0 / xp.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2] + out[3] * out[3])
    return pos + [o * inv_norm for o in out], vel + om
