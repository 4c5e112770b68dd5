"""The rigid quadcopter's control step as one Pallas kernel: every substep of the on-board controller and the
rigid-body physics for a block of envs, each env's state in registers from the first substep to the last.

Why: on the XLA path a control step of the Goto tasks is 30 substeps of :meth:`envs.quadcopter.robot.Quadcopter.
controller` + :meth:`envs.quadcopter.rigid_body.RigidBodySim.physics_step`, which XLA splits into several batch-wide kernels,
so the whole env state goes through memory many times per control step. Here each env reads its 13 state floats
and 4 command floats once and writes 13, whatever the number of substeps.

What it computes: the same equations in the same order, written per coordinate over ``[block]`` vectors (Triton
has no slice, so a state is a list of 7 + 6 vectors rather than one array), except that the controller takes the
heading's cosine and sine and the cosines of roll and pitch from the quaternion algebraically instead of through
the angles (fewer transcendental calls, the kernel's main cost), and divides by a constant or by one value
several times as a multiplication by its reciprocal (a float32 division is a short routine on a GPU, a
multiplication one instruction; the two differ by at most a rounding), with the constants baked in from the
robot (its :class:`~envs.quadcopter.robot.ControllerGains`, mass, inertia, unmix matrix and motor limits) and the
simulator's :class:`~envs.quadcopter.rigid_body.Airframe`. XLA and Triton round some operations differently in the last bit
(the dot products are written out, the rewritten cosines and divisions above, ``atan2``/``sin``/``cos`` from
another library on a GPU), so a control step agrees with the XLA path to float32 round-off, not bit for bit
(``tests/test_quadcopter_kernel.py``).

How it is used: :func:`make_advance` builds the batch function the robot offers as ``advance_kernel``
(:class:`jaxrobo.task.robot.Robot`); under ``ExecutionPlan(fused="pallas")`` :meth:`jaxrobo.physics.sim.Simulator.advance`
runs a vmapped control step through it, one kernel call for the whole batch. On a CPU it runs interpreted (the
tests' oracle checks), on a GPU through Triton.

Public surface: :func:`make_advance`, :func:`control_step` (the per-coordinate step, for any array shape) with
its :class:`Constants` (:func:`constants_of`), :data:`BLOCK`.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.api import JointState

#: Envs per Pallas program (a power of two, as Triton's blocks are). On an H100 one env per thread ran fastest
#: (blocks of 32-128 envs at 1-4 warps alike; two envs per thread 0.67-0.95x), and 128 fills more SMs than 256
#: at small batches (1.15x at 1,024 envs, 0.97x at 65,536, 1.0x at 1 M; docs/benchmarks.md, "Pallas: quadcopter").
BLOCK = 128


def _f32(v: Any) -> float:
    """A constant as the float32 the XLA path computes with (a Python float: weakly typed in the trace)."""
    return float(np.float32(v))


@dataclasses.dataclass(frozen=True)
class Constants:
    """Every number the control step needs, as float32 values (host; baked into the kernel)."""

    n_substeps: int
    dt: float
    # controller
    g: float
    mass: float
    inertia: tuple[float, float, float]
    unmix: tuple[tuple[float, ...], ...]  # [4 rotors][thrust, roll, pitch, yaw torque]
    ctrl_low: tuple[float, ...]
    ctrl_high: tuple[float, ...]
    k_vel_xy: float
    k_vel_z: float
    max_tilt: float
    a_max: float
    max_acc_up: float
    max_acc_down: float
    k_att: float
    k_rate: float
    k_yaw: float
    k_floor: float
    min_altitude: float
    # physics
    wrench: tuple[tuple[float, ...], ...]  # [6][rotor]: body force, torque per unit control
    body_inertia: tuple[float, float, float]
    body_mass: float
    gravity: tuple[float, float, float]


def constants_of(robot: Any) -> Constants:
    """The constants of a :class:`~envs.quadcopter.robot.Quadcopter` on the ``rigid`` backend."""
    sim, k = robot.sim, robot.gains
    af = sim.airframe
    return Constants(
        n_substeps=int(sim.n_substeps), dt=float(af.timestep), g=float(robot.g), mass=float(robot.mass),
        inertia=tuple(_f32(v) for v in robot.inertia),
        unmix=tuple(tuple(_f32(v) for v in row) for row in robot.unmix),
        ctrl_low=tuple(_f32(v) for v in robot.ctrl_low), ctrl_high=tuple(_f32(v) for v in robot.ctrl_high),
        k_vel_xy=float(k.k_vel_xy), k_vel_z=float(k.k_vel_z), max_tilt=float(k.max_tilt),
        a_max=_f32(robot.g * np.tan(k.max_tilt)), max_acc_up=float(k.max_acc_up), max_acc_down=float(k.max_acc_down),
        k_att=float(k.k_att), k_rate=float(k.k_rate), k_yaw=float(k.k_yaw), k_floor=float(k.k_floor),
        min_altitude=float(robot.min_altitude),
        wrench=tuple(tuple(_f32(v) for v in row) for row in af.wrench),
        body_inertia=tuple(_f32(v) for v in af.inertia), body_mass=float(af.mass),
        gravity=tuple(_f32(v) for v in af.gravity))


def _clip(x, low: float, high: float):
    # jnp.clip's order (max with the low bound, then min with the high one), skipping an infinite bound.
    if np.isfinite(low):
        x = jnp.maximum(x, low)
    if np.isfinite(high):
        x = jnp.minimum(x, high)
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


def _controller(c: Constants, q: Sequence[Any], v: Sequence[Any], cmd: Sequence[Any]) -> list:
    """:meth:`envs.quadcopter.robot.Quadcopter.controller`, per coordinate: rotor thrusts (N)."""
    w, x, y, z = q[3], q[4], q[5], q[6]
    roll_y, roll_x = 2 * (w * x + y * z), 1 - 2 * (x * x + y * y)
    roll = jnp.arctan2(roll_y, roll_x)
    sin_pitch = _clip(2 * (w * y - z * x), -1.0, 1.0)
    pitch = jnp.arcsin(sin_pitch)
    # The heading's cosine and sine, and cos(roll), cos(pitch), from the atan2/asin arguments instead of through
    # the angles (cos(atan2(y, x)) = x / hypot(x, y), cos(asin(s)) = sqrt(1 - s^2)): five transcendental calls
    # fewer per substep, equal to float32 round-off. The yaw angle itself is not needed.
    yaw_y, yaw_x = 2 * (w * z + x * y), 1 - 2 * (y * y + z * z)
    yaw_h = jnp.sqrt(yaw_x * yaw_x + yaw_y * yaw_y)
    level = yaw_h > 0  # atan2(0, 0) = 0: heading 0 where the heading is undefined (pitch +-90 degrees)
    inv_h = 1.0 / jnp.where(level, yaw_h, 1.0)
    cy, sy = jnp.where(level, yaw_x * inv_h, 1.0), jnp.where(level, yaw_y * inv_h, 0.0)
    roll_h = jnp.sqrt(roll_x * roll_x + roll_y * roll_y)
    cos_roll = jnp.where(roll_h > 0, roll_x / jnp.where(roll_h > 0, roll_h, 1.0), 1.0)
    cos_pitch = jnp.sqrt(jnp.maximum(1 - sin_pitch * sin_pitch, 0.0))
    vz_cmd = cmd[2]
    if c.min_altitude > 0:
        vz_cmd = jnp.maximum(vz_cmd, c.k_floor * (c.min_altitude - q[2]))
    vx_h, vy_h = cy * v[0] + sy * v[1], -sy * v[0] + cy * v[1]
    ax = _clip(c.k_vel_xy * (cmd[0] - vx_h), -c.a_max, c.a_max)
    ay = _clip(c.k_vel_xy * (cmd[1] - vy_h), -c.a_max, c.a_max)
    az = _clip(c.k_vel_z * (vz_cmd - v[2]), -c.max_acc_down, c.max_acc_up)
    pitch_d = _clip(jnp.arctan2(ax, c.g + az), -c.max_tilt, c.max_tilt)
    roll_d = _clip(jnp.arctan2(-ay, c.g + az), -c.max_tilt, c.max_tilt)
    thrust = c.mass * (c.g + az) / jnp.maximum(cos_roll * cos_pitch, 0.5)
    torque = [c.inertia[0] * (c.k_att * (roll_d - roll) - c.k_rate * v[3]),
              c.inertia[1] * (c.k_att * (pitch_d - pitch) - c.k_rate * v[4]),
              c.inertia[2] * (c.k_yaw * (cmd[3] - v[5]))]
    wanted = [thrust] + torque
    return [_clip(_dot(row, wanted), lo, hi) for row, lo, hi in zip(c.unmix, c.ctrl_low, c.ctrl_high)]


def _physics(c: Constants, q: Sequence[Any], v: Sequence[Any], ctrl: Sequence[Any]) -> tuple[list, list]:
    """:meth:`envs.quadcopter.rigid_body.RigidBodySim.physics_step`, per coordinate."""
    dt = c.dt
    ctrl = [_clip(u, lo, hi) for u, lo, hi in zip(ctrl, c.ctrl_low, c.ctrl_high)]
    wr = [_dot(row, ctrl) for row in c.wrench]
    qw, qx, qy, qz = q[3], q[4], q[5], q[6]
    rot = [[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
           [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
           [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]]
    force = wr[:3]
    acc = []
    for i in range(3):
        f = rot[i][0] * force[0] + rot[i][1] * force[1] + rot[i][2] * force[2]
        acc.append(f * _f32(1.0 / np.float32(c.body_mass)) + c.gravity[i])
    om = v[3:6]
    inertia = c.body_inertia
    l_mom = [inertia[i] * om[i] for i in range(3)]
    cross = [om[1] * l_mom[2] - om[2] * l_mom[1], om[2] * l_mom[0] - om[0] * l_mom[2],
             om[0] * l_mom[1] - om[1] * l_mom[0]]
    alpha = [(wr[3 + i] - cross[i]) * _f32(1.0 / np.float32(inertia[i])) for i in range(3)]
    vel = [v[i] + dt * acc[i] for i in range(3)]
    om = [om[i] + dt * alpha[i] for i in range(3)]
    pos = [q[i] + dt * vel[i] for i in range(3)]
    # quat_integrate: rotate by omega * dt about the body axes, then renormalise.
    angle = jnp.sqrt(om[0] * om[0] + om[1] * om[1] + om[2] * om[2]) * dt
    half = 0.5 * angle
    scale = jnp.where(angle > 1e-8, jnp.sin(half) / jnp.maximum(angle, 1e-8), 0.5 - half * half / 12.0) * dt
    bw, bx, by, bz = jnp.cos(half), om[0] * scale, om[1] * scale, om[2] * scale
    out = [qw * bw - qx * bx - qy * by - qz * bz, qw * bx + qx * bw + qy * bz - qz * by,
           qw * by - qx * bz + qy * bw + qz * bx, qw * bz + qx * by - qy * bx + qz * bw]
    inv_norm = 1.0 / jnp.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2] + out[3] * out[3])
    return pos + [o * inv_norm for o in out], vel + om


def control_step(c: Constants, q: Sequence[Any], v: Sequence[Any], cmd: Sequence[Any]) -> tuple[list, list]:
    """One control step (``c.n_substeps`` substeps of controller + physics) on per-coordinate arrays of any
    shape: 7 position coordinates, 6 velocity coordinates and 4 command values."""

    def substep(_, carry):
        q, v = list(carry[:7]), list(carry[7:])
        q, v = _physics(c, q, v, _controller(c, q, v, cmd))
        return tuple(q) + tuple(v)

    out = jax.lax.fori_loop(0, c.n_substeps, substep, tuple(q) + tuple(v))
    return list(out[:7]), list(out[7:])


def _kernel(c: Constants, n: int, block: int) -> Callable:
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    def kernel(qpos_ref, qvel_ref, cmd_ref, qpos_out, qvel_out):
        env = pl.program_id(0) * block + jax.lax.iota(jnp.int32, block)
        mask = env < n
        # Each env's row read and written word by word: the rows of a block are contiguous, so the words of
        # a row come from the same cache lines.
        q = [plgpu.load(qpos_ref.at[env * 7 + j], mask=mask, other=0.0) for j in range(7)]
        v = [plgpu.load(qvel_ref.at[env * 6 + j], mask=mask, other=0.0) for j in range(6)]
        cmd = [plgpu.load(cmd_ref.at[env * 4 + j], mask=mask, other=0.0) for j in range(4)]
        q, v = control_step(c, q, v, cmd)
        for j in range(7):
            plgpu.store(qpos_out.at[env * 7 + j], q[j], mask=mask)
        for j in range(6):
            plgpu.store(qvel_out.at[env * 6 + j], v[j], mask=mask)

    return kernel


def make_advance(robot: Any, block: int | None = None, num_warps: int | None = None,
                 interpret: bool | None = None) -> Callable[[JointState, jax.Array], JointState]:
    """The robot's control step over a batch: ``(JointState [n], command [n, 4]) -> JointState [n]``, one
    Pallas call. ``block``/``num_warps``: envs and warps per program (defaults :data:`BLOCK` and one
    thread per env); ``interpret``: run the kernel interpreted (default: unless JAX's default backend is a
    GPU)."""
    c = constants_of(robot)

    def advance(state: JointState, command: jax.Array) -> JointState:
        from jax.experimental import pallas as pl
        from jax.experimental.pallas import triton as plgpu

        n = state.qpos.shape[0]
        if n == 0:
            return state
        size = BLOCK if block is None else block
        size = min(size, max(1, 1 << (n - 1).bit_length()))  # a batch smaller than a block: one short program
        warps = max(1, min(8, size // 32)) if num_warps is None else num_warps  # default: one thread per env
        run_interpreted = jax.default_backend() != "gpu" if interpret is None else interpret
        params = None if run_interpreted else plgpu.CompilerParams(num_warps=warps, num_stages=1)
        whole = pl.BlockSpec(memory_space=pl.ANY)
        flat = lambda x: jnp.asarray(x, jnp.float32).reshape(-1)  # noqa: E731
        qpos, qvel = pl.pallas_call(
            _kernel(c, n, size), grid=(-(-n // size),), in_specs=[whole] * 3, out_specs=[whole] * 2,
            out_shape=[jax.ShapeDtypeStruct((n * 7,), jnp.float32), jax.ShapeDtypeStruct((n * 6,), jnp.float32)],
            interpret=run_interpreted, compiler_params=params, name="quadcopter_control_step",
        )(flat(state.qpos), flat(state.qvel), flat(command))
        return JointState(qpos.reshape(n, 7), qvel.reshape(n, 6))

    return advance
