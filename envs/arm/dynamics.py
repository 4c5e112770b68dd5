"""Closed-form dynamics of the planar arm: the arm's fast backend (``analytic``).

Two links turning about parallel vertical hinges have a 2×2 mass matrix with one configuration-dependent term, so
a whole MuJoCo step reduces to a few dozen multiply-adds. :class:`ArmSim` evaluates them with every constant read
from the compiled :class:`mujoco.MjModel` (each link's mass, centre of mass and inertia about the hinge axis, the
forearm's offset, joint damping and armature, the timestep, each servo's gain, bias and limits), so the MJCF stays
the single source of truth, and refuses a model it cannot reproduce (joint limits, contacts, stiffness, friction,
activation dynamics, a tilted axis, gravity off the hinge axes). It mirrors MuJoCo's Euler step with implicit
joint damping and agrees with native MuJoCo to float64 round-off (``tests/test_arm_reach.py``).

Why it exists: MJX steps the arm through its general pipeline (kinematics, composite inertias, recursive Newton-Euler,
two factorisations), about 1,700 operations of a training chunk's program that XLA compiles for several seconds
on a GPU (docs/benchmarks.md); the closed form is a few dozen. ``mjx`` checks a result against the maintained
engine; ``analytic`` is the default preset's backend.

Coordinates (MuJoCo's, in the order of ``qpos``): ``q1`` the shoulder, ``q2`` the elbow (rad), both about +z.
With ``c1`` the upper arm's centre of mass in its frame, ``p`` the elbow's position in the upper arm's frame, ``c2``
the forearm's centre of mass in its frame, ``m_i`` the masses and ``I_i`` the inertias about +z through the centres
of mass (only the in-plane parts of the vectors count)::

    k(q2) = m2 (p·c2 cos q2 + (p × c2) sin q2)
    M(q)  = [[m1 |c1|² + I1 + m2 (|p|² + |c2|²) + I2 + 2 k + a1,  m2 |c2|² + I2 + k],
             [m2 |c2|² + I2 + k,                                    m2 |c2|² + I2 + a2]]
    M q̈ = τ - D q̇ - [k' q̇2 (2 q̇1 + q̇2),  -k' q̇1²]

with ``k' = dk/dq2``, ``a`` the armatures, ``D`` the joint damping and ``τ`` the servos' torques. Gravity along the
hinge axes does no work. MuJoCo's Euler integrates the damping implicitly: ``(M + h D) q̈ = τ - D q̇ - bias``, then
``q̇ += h q̈`` and ``q += h q̇``.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxrobo.api import ClosedFormSim, JointState, actuators

#: Domain randomisation's factors the closed form takes (the same as MJX's edit of the model in
#: :meth:`envs.arm.robot.ArmRobot.sim_physics`): both links' masses and inertias, and both joints' damping.
FACTORS = ("link_mass", "damping")


@dataclasses.dataclass(frozen=True)
class ArmConstants:
    """The arm's constants, read from a compiled model (host floats; baked into the trace)."""

    inertia_straight: float  # m1 |c1|² + I1 + m2 (|p|² + |c2|²) + I2 (kg m²): the shoulder's, less 2 k
    inertia_fore: float  # m2 |c2|² + I2 (kg m²): the forearm's about the elbow
    coupling_cos: float  # m2 p·c2 (kg m²): k's cos q2 term
    coupling_sin: float  # m2 (p × c2)_z (kg m²): k's sin q2 term
    armature: tuple[float, float]
    damping: tuple[float, float]  # (N m s/rad)
    actuators: tuple  # per servo, what jaxrobo.physics.actuators.generalized_forces reads


def _refuse(condition: bool, why: str) -> None:
    if condition:
        raise ValueError(f"the analytic arm backend cannot model this MJCF: {why}; use backend='mjx'")


def _inertia_z(m: mujoco.MjModel, body: int) -> float:
    """The body's inertia about +z through its centre of mass (kg m²), from its principal inertia and frame."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.body_iquat[body])
    rot = rot.reshape(3, 3)
    return float((rot @ np.diag(m.body_inertia[body]) @ rot.T)[2, 2])


def constants_from_model(mj_model: mujoco.MjModel, joints: tuple[str, str]) -> ArmConstants:
    """Read the arm's constants from ``mj_model``, ``joints`` the shoulder's and the elbow's names; refuse anything
    the closed form does not describe."""
    m = mj_model
    jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name) for name in joints]
    _refuse(min(jid) < 0, f"joints {joints[0]!r} and {joints[1]!r} must both exist")
    _refuse(m.njnt != 2 or m.nbody != 3, "exactly world + upper arm + forearm bodies, one joint each")
    _refuse(any(m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE for j in jid), "both joints must be hinges")
    upper, fore = (int(m.jnt_bodyid[j]) for j in jid)
    _refuse(m.body_parentid[upper] != 0 or m.body_parentid[fore] != upper,
            "the forearm's body must be a child of the upper arm's, and that of the world")
    for b in (upper, fore):
        _refuse(np.abs(m.body_quat[b] - [1, 0, 0, 0]).max() > 1e-9, "body frames must be aligned with the world")
    for j in jid:
        _refuse(np.abs(m.jnt_axis[j] - [0, 0, 1]).max() > 1e-9, "the hinge axes must be +z")
        _refuse(np.abs(m.jnt_pos[j]).max() > 1e-9, "each hinge must sit at its body's origin")
    _refuse((tuple(m.jnt_qposadr[jid]), tuple(m.jnt_dofadr[jid])) != ((0, 1), (0, 1)),
            "the shoulder's coordinate must come first in qpos and qvel")
    _refuse(bool(m.jnt_limited.any()), "joint limits are constraints")
    _refuse(m.neq > 0 or m.ntendon > 0, "equality constraints or tendons")
    _refuse(bool(np.any(m.dof_frictionloss) or np.any(m.jnt_stiffness)), "joint friction loss or stiffness")
    _refuse(not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT), "contacts must be disabled")
    _refuse(m.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER, "the closed form mirrors the Euler integrator")
    _refuse(bool(m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP),
            "the closed form integrates the joint damping implicitly, as MuJoCo's Euler does by default")
    _refuse(bool(m.opt.density or m.opt.viscosity), "fluid forces")
    _refuse(np.abs(m.opt.gravity[:2]).max() > 0, "gravity must point along the hinge axes (z)")
    m1, m2 = float(m.body_mass[upper]), float(m.body_mass[fore])
    c1, c2, p = (np.asarray(v, np.float64)[:2] for v in (m.body_ipos[upper], m.body_ipos[fore], m.body_pos[fore]))
    i1, i2 = _inertia_z(m, upper), _inertia_z(m, fore)
    inertia_fore = m2 * float(c2 @ c2) + i2
    return ArmConstants(
        inertia_straight=m1 * float(c1 @ c1) + i1 + m2 * float(p @ p) + inertia_fore,
        inertia_fore=inertia_fore,
        coupling_cos=m2 * float(p @ c2), coupling_sin=m2 * float(p[0] * c2[1] - p[1] * c2[0]),
        armature=(float(m.dof_armature[0]), float(m.dof_armature[1])),
        damping=(float(m.dof_damping[0]), float(m.dof_damping[1])),
        actuators=actuators.actuator_rows(**actuators.joint_actuators(m, _refuse)))


def accelerations(c: ArmConstants, q: Any, v: Any, ctrl: Any, dt: float, physics: dict | None = None
                  ) -> tuple[Any, Any]:
    """``(q̈1, q̈2)`` of MuJoCo's Euler step with implicit damping, for joint angles ``q`` and rates ``v`` (pairs of
    scalars or same-shape arrays), ``ctrl[j]`` servo j's set-point; ``physics``: one env's factors (domain
    randomisation, :data:`FACTORS`), each multiplying the constants it scales. Without them the constants stay host
    floats, so sums of constants are made on the host in float64 (factors of 1 give the same values to float32
    round-off, not bit for bit)."""
    straight, fore, k_cos, k_sin = c.inertia_straight, c.inertia_fore, c.coupling_cos, c.coupling_sin
    d1, d2 = c.damping
    if physics is not None:
        mass, damp = physics["link_mass"], physics["damping"]
        straight, fore, k_cos, k_sin = straight * mass, fore * mass, k_cos * mass, k_sin * mass
        d1, d2 = d1 * damp, d2 * damp
    sin, cos = jnp.sin(q[1]), jnp.cos(q[1])
    k = k_cos * cos + k_sin * sin
    dk = k_sin * cos - k_cos * sin  # dk/dq2
    tau = actuators.generalized_forces(c.actuators, q, v, ctrl)
    rhs1 = tau[0] - d1 * v[0] - dk * v[1] * (2.0 * v[0] + v[1])
    rhs2 = tau[1] - d2 * v[1] + dk * v[0] * v[0]
    # M + h D, solved in closed form.
    m11 = straight + 2.0 * k + (c.armature[0] + dt * d1)
    m12 = fore + k
    m22 = fore + (c.armature[1] + dt * d2)
    inv_det = 1.0 / (m11 * m22 - m12 * m12)
    return (m22 * rhs1 - m12 * rhs2) * inv_det, (m11 * rhs2 - m12 * rhs1) * inv_det


class ArmSim(ClosedFormSim):
    """A :class:`~jaxrobo.physics.sim.ClosedFormSim` over the closed-form arm (backend ``analytic``)."""

    def __init__(self, mj_model: mujoco.MjModel, joints: tuple[str, str], running_step: float | None = None):
        self.constants = constants_from_model(mj_model, joints)
        super().__init__(mj_model, "analytic", running_step)

    def physics_step(self, state: JointState, ctrl: jax.Array, physics: dict | None = None) -> JointState:
        """One step (MuJoCo's semi-implicit Euler: velocities first, positions with the new velocities);
        ``physics``: one env's factors (domain randomisation, :data:`FACTORS`)."""
        q, v = state.qpos, state.qvel
        acc = jnp.stack(accelerations(self.constants, q, v, ctrl, self.timestep, physics))
        v = v + self.timestep * acc
        return JointState(q + self.timestep * v, v)

