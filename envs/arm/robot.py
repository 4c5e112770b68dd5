"""The planar arm robot (the robot env of openai_ros' reach tasks): model, position controllers, joint and
fingertip sensors.

The MJCF (``envs/arm/arm.xml``) states the link lengths, masses and servo gains: two hinges about z (shoulder,
elbow) in the horizontal plane, each driven by an MJCF ``position`` actuator. The task's command is the pair of
joint-angle set-points (rad); the servos track them inside the physics (``torque = kp (u - q)``), so the robot's
controller is the default pass-through. The elbow's set-point is clamped to ``[0, ELBOW_MAX]`` by the actuator's
``ctrlrange``: the arm bends one way, and each fingertip position has one joint solution.

Sensors: the joint angles and rates, and the fingertip (the MJCF's ``fingertip`` site) from the joint angles by
the arm's forward kinematics, which equals MuJoCo's site position (``tests/test_arm_reach.py`` checks it).

Backends: ``mjx`` (MuJoCo MJX, the task's default), Brax's pipelines (:func:`jaxrobo.physics.sim.backend_choices`)
and ``analytic``, the closed form of the same MJCF (``envs/arm/dynamics.py``; the default preset's).
"""
from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco

from envs.arm.dynamics import FACTORS, ArmSim
from jaxrobo.api import MjxEdit, Robot, backend_choices, load_model, make_simulator

#: The robot's MJCF, beside this module.
MJCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "arm.xml")
JOINTS = ("shoulder", "elbow")
#: Upper arm and forearm lengths (m), as in the MJCF (checked against it when the robot is built).
UPPER, FORE = 0.5, 0.4
#: The elbow servo's set-point range (rad), the MJCF's ``ctrlrange``.
ELBOW_MAX = 2.8
#: The arm's hand-written backend, beside every engine of :mod:`jaxrobo.physics.sim`.
CLOSED_FORM = {"analytic": lambda mj_model, running_step: ArmSim(mj_model, JOINTS, running_step)}
BACKENDS = backend_choices(CLOSED_FORM)


def fingertip(q: Any, xp: Any = jnp) -> Any:
    """Forward kinematics: the fingertip ``(x, y)`` (m) for joint angles ``q = [shoulder, elbow]`` (rad), over the
    array module ``xp``: ``jax.numpy`` in the env (under ``jit``/``vmap``), ``numpy`` in the native port
    (``envs/arm/native.py``), so both run this one source."""
    a = q[..., 0] + q[..., 1]
    return xp.stack([UPPER * xp.cos(q[..., 0]) + FORE * xp.cos(a), UPPER * xp.sin(q[..., 0]) + FORE * xp.sin(a)],
                    axis=-1)


class ArmRobot(Robot):
    """Two hinges under position control; the command is ``[shoulder, elbow]`` set-points (rad)."""

    def __init__(self, backend: str = "mjx", running_step: float = 0.1, timestep: float = 0.01):
        mj_model = load_model(MJCF, timestep=timestep)
        # MJX integrates the model without its light, camera, floor and base (same dynamics, less work).
        physics = lambda: load_model(MJCF, timestep=timestep, physics_only=True)  # noqa: E731
        super().__init__(make_simulator(mj_model, backend, running_step, physics, closed_form=CLOSED_FORM))
        ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in JOINTS]
        self.q = tuple(int(mj_model.jnt_qposadr[i]) for i in ids)
        self.v = tuple(int(mj_model.jnt_dofadr[i]) for i in ids)
        elbow = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_ACTUATOR, "elbow")
        # The closed-form fingertip and the set-point clamp must describe this MJCF, not an edited copy of it.
        fore = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, "fore")
        tip = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, "fingertip")
        got = (float(mj_model.body_pos[fore][0]), float(mj_model.site_pos[tip][0]),
               float(mj_model.actuator_ctrlrange[elbow][1]))
        if got != (UPPER, FORE, ELBOW_MAX):
            raise ValueError(f"{MJCF}: upper arm, forearm and elbow range are {got}; envs/arm/robot.py expects "
                             f"{(UPPER, FORE, ELBOW_MAX)}")

    def randomisable(self) -> tuple[str, ...]:
        """``link_mass`` (a factor on both links' masses and inertias) and ``damping`` (a factor on the joints'
        damping), on ``mjx`` and ``analytic``; Brax's pipelines: none."""
        return FACTORS if self.sim.backend in ("analytic", "mjx") else ()

    def sim_physics(self, domain: dict[str, jax.Array]) -> Any:
        """A drawn domain as the closed form's factors, or as MJX model fields."""
        one = jnp.ones((), jnp.float32)
        f = {name: domain.get(name, one) for name in FACTORS}
        if self.sim.backend == "analytic":
            return f
        m = self.sim.model
        mass = f["link_mass"]
        return MjxEdit(model={"body_mass": m.body_mass * mass, "body_inertia": m.body_inertia * mass,
                              "dof_damping": m.dof_damping * f["damping"]}, data={})

    def init_pose(self, q: jax.Array, qdot: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
        """``(qpos, qvel)`` for joint angles ``q = [shoulder, elbow]`` (rad) and their rates (rad/s, default 0)."""
        qdot = jnp.zeros(2) if qdot is None else qdot
        qpos = jnp.zeros(2).at[jnp.asarray(self.q)].set(q)
        qvel = jnp.zeros(2).at[jnp.asarray(self.v)].set(qdot)
        return qpos, qvel

    def joint_angles(self, pipeline_state: Any) -> jax.Array:
        """``[shoulder, elbow]`` (rad)."""
        return self.sim.qpos(pipeline_state)[jnp.asarray(self.q)]

    def read_sensors(self, pipeline_state: Any) -> dict[str, jax.Array]:
        """``q`` (joint angles, rad), ``qdot`` (joint rates, rad/s), ``tip`` (fingertip ``(x, y)``, m)."""
        q = self.joint_angles(pipeline_state)
        return {"q": q, "qdot": self.sim.qvel(pipeline_state)[jnp.asarray(self.v)], "tip": fingertip(q)}
