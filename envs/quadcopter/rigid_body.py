"""Hand-written dynamics of one free rigid body driven by actuator wrenches: the quadcopter's fast backend.

A contact-free quadrotor is one free body and four constant body-frame wrenches, so its whole MuJoCo step reduces to
Newton–Euler plus a quaternion update. :class:`RigidBodySim` does exactly that, with every constant (mass, inertia,
timestep, gravity, each actuator's body-frame force and torque per unit control, control limits) read from the compiled
:class:`mujoco.MjModel`, so the MJCF stays the single source of truth. It mirrors MuJoCo's semi-implicit Euler
(velocities first, then positions with the new velocities; quaternions integrated in the body frame as
``mju_quatIntegrate`` does), so it agrees with MJX to float32 round-off over seconds of flight (see
``tests/test_quadcopter.py``). The equations themselves live in :mod:`envs.quadcopter.dynamics`, written per coordinate
so that the Pallas kernels run the same source; this module reads the constants and splits the state into coordinates
and back. It subclasses :class:`jaxrobo.physics.sim.ClosedFormSim`, so the robot, the tasks and ``advance`` (the
controller every substep) are shared with the MJX backend.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs.quadcopter.dynamics import body_constants, physics_step
from jaxrobo.api import ClosedFormSim, JointState


@dataclasses.dataclass(frozen=True)
class Airframe:
    """Constants of a one-body vehicle, derived from a compiled model (host numpy; baked into the trace)."""

    mass: float
    inertia: np.ndarray  # [3] principal moments about the CoM, body axes (kg m^2)
    wrench: np.ndarray  # [6, n_act] body-frame [force; torque about the CoM] per unit control
    ctrl_low: np.ndarray
    ctrl_high: np.ndarray
    gravity: np.ndarray  # [3] m/s^2
    timestep: float


def _quat_mat(q: np.ndarray) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, np.float64))
    return m.reshape(3, 3)


def airframe_from_model(mj_model: mujoco.MjModel, body: str = "drone") -> Airframe:
    """Read mass, inertia and the actuator wrench map of ``body`` from the model; refuse what it cannot model."""
    bid = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise ValueError(f"model has no body {body!r}")
    if mj_model.nbody != 2 or mj_model.njnt != 1 or mj_model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        raise ValueError("the rigid backend models exactly one free body (world + 1 body, one free joint)")
    if np.linalg.norm(mj_model.body_ipos[bid]) > 1e-9 or np.linalg.norm(mj_model.body_iquat[bid] - [1, 0, 0, 0]) > 1e-9:
        raise ValueError("the rigid backend needs the CoM at the body origin and principal axes = body axes")
    if not (mj_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT):
        raise ValueError("the rigid backend has no contacts: disable them in the MJCF (<flag contact='disable'/>)")
    if mj_model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        raise ValueError("the rigid backend mirrors the Euler integrator; set integrator='Euler' in the MJCF")
    if np.any(mj_model.dof_damping) or np.any(mj_model.dof_armature) or mj_model.opt.density or mj_model.opt.viscosity:
        raise ValueError("the rigid backend has no damping, armature or fluid forces")
    wrench = np.zeros((6, mj_model.nu))
    for i in range(mj_model.nu):
        if mj_model.actuator_trntype[i] != mujoco.mjtTrn.mjTRN_SITE or mj_model.actuator_dyntype[i] != 0:
            raise ValueError("the rigid backend needs site actuators without activation dynamics")
        if mj_model.actuator_gaintype[i] != 0 or mj_model.actuator_biastype[i] != 0:
            raise ValueError("the rigid backend needs fixed-gain actuators without bias")
        sid = mj_model.actuator_trnid[i, 0]
        if mj_model.site_bodyid[sid] != bid:
            raise ValueError(f"actuator {i} acts on another body")
        gain = float(mj_model.actuator_gainprm[i, 0])
        rot = _quat_mat(mj_model.site_quat[sid])
        force = rot @ mj_model.actuator_gear[i, :3] * gain
        torque = rot @ mj_model.actuator_gear[i, 3:] * gain + np.cross(mj_model.site_pos[sid], force)
        wrench[:, i] = np.concatenate([force, torque])
    limited = mj_model.actuator_ctrllimited.astype(bool)
    low = np.where(limited, mj_model.actuator_ctrlrange[:, 0], -np.inf)
    high = np.where(limited, mj_model.actuator_ctrlrange[:, 1], np.inf)
    return Airframe(float(mj_model.body_mass[bid]), np.array(mj_model.body_inertia[bid]), wrench, low, high,
                    np.array(mj_model.opt.gravity), float(mj_model.opt.timestep))


class RigidBodySim(ClosedFormSim):
    """A :class:`~jaxrobo.physics.sim.ClosedFormSim` over Newton–Euler for one free body (backend ``rigid``).

    Its state is a :class:`~jaxrobo.physics.sim.JointState` of the free joint: ``qpos = [pos (world), quat wxyz]``,
    ``qvel = [linear velocity (world), angular velocity (body frame)]``."""

    def __init__(self, mj_model: mujoco.MjModel, running_step: float | None = None, body: str = "drone"):
        self.airframe = airframe_from_model(mj_model, body)
        self.constants = body_constants(self.airframe)
        super().__init__(mj_model, "rigid", running_step)

    def physics_step(self, state: JointState, ctrl: jax.Array, physics: dict | None = None) -> JointState:
        """One step; ``physics`` (domain randomisation, :meth:`envs.quadcopter.robot.Quadcopter.sim_physics`):
        this env's factors on mass (and inertia) and motor gain, and a world-frame force (wind)."""
        # The equations per coordinate (envs/quadcopter/dynamics.py, which the Pallas kernels run too): the state
        # split into its coordinates along the last axis, stepped, and stacked back.
        q = [state.qpos[..., i] for i in range(7)]
        v = [state.qvel[..., i] for i in range(6)]
        q, v = physics_step(jnp, self.constants, q, v, [ctrl[..., j] for j in range(ctrl.shape[-1])], physics)
        return JointState(jnp.stack(q, axis=-1), jnp.stack(v, axis=-1))
